"""recorder over real DDS: every contract topic into a rosbag2 (MCAP) bag, with metadata."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PolygonInstanceStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from ros_helpers import SEED, stamp_ns
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.typesys import Stores, get_typestore
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.recording import bags
from msg_schemas import TOPICS


def _bag_counts(bag: Path) -> tuple[dict[str, int], dict[str, list], dict]:
    typestore = get_typestore(Stores.ROS2_JAZZY)
    counts: dict[str, int] = {}
    messages: dict[str, list] = {}
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            message = typestore.deserialize_cdr(raw, connection.msgtype)
            messages.setdefault(connection.topic, []).append(message)
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
        types = {c.topic: c for c in reader.connections}
    return counts, messages, types


def test_recorder_writes_every_topic_and_metadata(ros, sim, processes, tmp_path):
    bag, metadata_file = tmp_path / "bag", tmp_path / "trial.json"
    metadata_file.write_text(json.dumps({"scenario": "two_zones", "result": None}))
    recorder, log = processes.start("recorder",
                                    output=bag, metadata_file=metadata_file)
    published = {"plan": PathMsg, "diagnostics": DiagnosticArray,
                 "zone_markers": MarkerArray, "zones": PolygonInstanceStamped,
                 "keepout_mask": OccupancyGrid}
    publishers = {topic: ros.publisher(topic, msg_type) for topic, msg_type in published.items()}

    def recorder_matched_all() -> bool:
        text = log.read_text()
        return all(f"{e.resolved()}: 1 publisher(s) matched" in text for e in TOPICS.values()) \
            and sim.setpoint_pub.get_subscription_count() >= 2 \
            and all(p.get_subscription_count() >= 1 for p in publishers.values())

    assert ros.spin_until(recorder_matched_all), f"recorder not matched:\n{log.read_text()}"

    assert sim.reset(SEED).success  # stamps restart at 0: the steps below are told apart
    before = sim.stamps()
    for i in range(3):  # one at a time: each answers the observation in force
        sim.send(150.0 + 10 * i, 300.0)
        sim.wait_new_stamps(sim.stamps(), 1)
    new = sim.stamps()[len(before):]
    for i in range(2):
        publishers["plan"].publish(PathMsg())
        publishers["diagnostics"].publish(
            DiagnosticArray(status=[DiagnosticStatus(name="policy", message=str(i))]))
        publishers["zone_markers"].publish(MarkerArray())
        zone = PolygonInstanceStamped()
        zone.polygon.id = 40 + i
        publishers["zones"].publish(zone)
        publishers["keepout_mask"].publish(OccupancyGrid())

    def recorded_all() -> bool:  # what the recorder has flushed holds every message published
        held = bags.read_unfinished(bag)
        return len(held.get(TOPICS["setpoint"].resolved(), [])) >= sim.sent and all(
            len(held.get(TOPICS[topic].resolved(), [])) >= 2 for topic in published)

    # Not a fixed wait: on a busy machine a reliable sample can take a retransmission to arrive.
    assert ros.spin_until(recorded_all), f"recorder did not get everything:\n{log.read_text()}"
    metadata_file.write_text(json.dumps({"scenario": "two_zones", "result": {"score": 0.5}}))
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(timeout=15) == 0, log.read_text()

    counts, messages, connections = _bag_counts(bag)
    assert (bag / "bag.mcap").is_file()
    # Publishers keep their history (transient local) and the recorder asks for it, so the bag
    # holds every setpoint this session published, from before the recorder started too.
    assert counts["/pusht/setpoint"] == sim.sent
    for topic in published:
        assert counts.get(TOPICS[topic].resolved()) == 2, topic
    for topic in ("/pusht/pusher", "/pusht/keypoints", "/pusht/block_pose"):
        recorded = [stamp_ns(m.header.stamp) for m in messages[topic]]
        recorded = recorded[len(recorded) - recorded[::-1].index(0):]  # since the last reset
        assert set(new) <= set(recorded), topic
        assert all(recorded.count(s) == 1 for s in new[:-1]), topic  # no step recorded twice
    assert counts["/pusht/score"] >= 3
    assert sorted(m.polygon.id for m in messages["/pusht/zones"]) == [40, 41]
    by_name = {endpoint.resolved(): endpoint for endpoint in TOPICS.values()}
    for topic, connection in connections.items():
        assert connection.msgtype == by_name[topic].type
        assert connection.digest.startswith("RIHS01_")
    assert connections["/pusht/zones"].ext.offered_qos_profiles[0].durability.name == \
        "TRANSIENT_LOCAL"

    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap"
    custom = info["custom_data"]
    assert json.loads(custom["trial_metadata"]) == {"scenario": "two_zones",
                                                   "result": {"score": 0.5}}
    recorded_counts = json.loads(custom["message_counts"])
    assert set(recorded_counts) == set(by_name)
    assert {t: n for t, n in recorded_counts.items() if n} == counts
    assert "closed" in log.read_text() and "Traceback" not in log.read_text()


def test_recorder_refuses_existing_bag(processes, tmp_path):
    (tmp_path / "bag").mkdir()
    recorder, log = processes.start("recorder_exists", "recorder",
                                    output=tmp_path / "bag")
    assert recorder.wait(timeout=20) != 0
    text = log.read_text()
    assert "exists" in text and "Traceback" not in text


def test_a_recorder_killed_mid_trial_keeps_what_it_had_a_second_before(ros, sim, processes,
                                                                       tmp_path):
    """SIGKILL while the sim steps: metadata.yaml was valid from the start, the bag does not
    open until `recover_bag` indexes it, and then holds the observations the test had received
    up to one second before the kill (the recorder subscribes to the same topic)."""
    bag, metadata_file = tmp_path / "bag", tmp_path / "trial.json"
    metadata_file.write_text(json.dumps({"scenario": "killed"}))
    recorder, log = processes.start("recorder_killed", "recorder", output=bag,
                                    metadata_file=metadata_file)
    pusher = TOPICS["pusher"].resolved()
    assert ros.spin_until(lambda: f"{pusher}: 1 publisher(s) matched" in log.read_text()
                          and sim.setpoint_pub.get_subscription_count() >= 2), log.read_text()
    information = yaml.safe_load((bag / "metadata.yaml").read_text())
    assert information["rosbag2_bagfile_information"]["relative_file_paths"] == ["bag.mcap"]
    assert "recover_bag" in information["rosbag2_bagfile_information"]["custom_data"]["recorder"]

    assert sim.reset(SEED).success
    received_at: dict[int, float] = {}  # observation stamp -> when the test had it
    start = time.monotonic()
    while time.monotonic() - start < 4.0:
        before = sim.stamps()
        sim.send(150.0 + 50.0 * ((time.monotonic() - start) % 2.0), 300.0)
        for stamp in sim.wait_new_stamps(before, 1):
            received_at[stamp] = time.monotonic()
    recorder.send_signal(signal.SIGKILL)
    killed = time.monotonic()
    assert recorder.wait(timeout=10) == -signal.SIGKILL

    with pytest.raises(ReaderError):
        _bag_counts(bag)
    unfinished = bags.read_unfinished(bag)  # as a trial reads its bag while it is recorded
    assert bags.main([str(bag)]) == 0
    counts, messages, _ = _bag_counts(bag)
    assert {topic: len(listed) for topic, listed in unfinished.items()} == counts
    assert unfinished[pusher] == messages[pusher]
    recorded = [stamp_ns(m.header.stamp) for m in messages[pusher]]
    recorded = set(recorded[len(recorded) - recorded[::-1].index(0):])  # since the reset
    due = [stamp for stamp, at in received_at.items() if at <= killed - 1.0]
    assert len(due) >= 20, len(due)  # the sim stepped for three seconds before that
    kept = len(recorded & set(due))
    print(f"recovered {kept} of the {len(due)} observations received up to 1 s before the kill; "
          f"{len(recorded)} of {len(received_at)} in all")
    assert kept >= 0.95 * len(due), (kept, len(due))
    information = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert information["message_count"] == sum(counts.values())
    assert json.loads(information["custom_data"]["message_counts"]) == counts
    assert "recovered" in information["custom_data"]["recorder"]
    assert json.loads(information["custom_data"]["trial_metadata"]) == {"scenario": "killed"}
    # Less than rosbags' own 1 MiB chunk: what was kept came from the recorder's flushes.
    assert (bag / "bag.mcap.unindexed").stat().st_size < 2**20
    assert bags.main([str(bag)]) == 0  # complete now: left as it is
    assert _bag_counts(bag)[0] == counts
