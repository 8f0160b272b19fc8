"""The ROS nodes over real DDS: each node in its own process, an rclpy test node in this one.

Every run uses a random ROS domain, so parallel runs on one machine do not hear each other, and
waits on discovery by polling match counts (or the recorder's log of them), never on blind sleeps.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PointStamped, PolygonInstanceStamped, PolygonStamped, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import Processes, Ros, random_domain_id, stamp_ns
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import Float64
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from msg_schemas import FRAME_ID, SERVICES, TOPICS, qos_profile
from sim_bridge.pusht import PushTSim, seeded_state

DOMAIN_ID = random_domain_id()
SEED = 100000


def step_ns(step: int) -> int:
    return step * 100_000_000


@pytest.fixture(scope="module")
def ros():
    handle = Ros(DOMAIN_ID, "test_ros_nodes")
    yield handle
    handle.close()


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("ros_nodes")


@pytest.fixture
def processes(log_dir):
    started = Processes(log_dir, DOMAIN_ID)
    yield started
    started.stop_all()


class SimLink:
    """The sim_node process and the test node's side of its topics."""

    def __init__(self, ros: Ros, process: subprocess.Popen, log: Path) -> None:
        self.ros, self.process, self.log = ros, process, log
        self.pushers = ros.inbox("pusher", PointStamped)
        self.keypoints = ros.inbox("keypoints", PolygonStamped)
        self.poses = ros.inbox("block_pose", PoseStamped)
        self.scores = ros.inbox("score", Float64)
        self.setpoint_pub = ros.publisher("setpoint", PointStamped)
        self.sent = 0  # setpoints published, all kept in the publisher's history
        self.reset_client = ros.node.create_client(Trigger, SERVICES["reset"].name)
        self.params = AsyncParameterClient(ros.node, "sim_node")

    def stamps(self) -> list[int]:
        """Distinct observation stamps in arrival order (the sim re-sends while idle)."""
        return list(dict.fromkeys(stamp_ns(m.header.stamp) for m in self.pushers))

    def latest(self) -> PointStamped:
        return self.pushers[-1]

    def send(self, x: float, y: float, stamp=None) -> None:
        msg = PointStamped()
        msg.header.stamp = stamp if stamp is not None else self.latest().header.stamp
        msg.header.frame_id = FRAME_ID
        msg.point.x, msg.point.y = float(x), float(y)
        self.setpoint_pub.publish(msg)
        self.sent += 1

    def wait_new_stamps(self, before: list[int], n: int, timeout: float = 10.0) -> list[int]:
        assert self.ros.spin_until(lambda: len(self.stamps()) >= len(before) + n, timeout), \
            f"expected {n} new observations, got {len(self.stamps()) - len(before)}"
        return self.stamps()[len(before):]

    def reset(self, seed: int) -> Trigger.Response:
        """Set the seed parameter, call the reset service, wait for the new scene's first
        observation and forget the observations before it (stamps start again at 0)."""
        future = self.params.set_parameters([Parameter("seed", value=seed)])
        assert self.ros.spin_until(future.done, 10.0), "setting the seed parameter timed out"
        assert future.result().results[0].successful
        mark = len(self.pushers)
        future = self.reset_client.call_async(Trigger.Request())
        assert self.ros.spin_until(future.done, 10.0), "reset service timed out"
        if future.result().success:
            start = tuple(seeded_state(seed)[:2])

            def first_of_scene() -> int | None:
                return next((i for i in range(mark, len(self.pushers))
                             if stamp_ns(self.pushers[i].header.stamp) == 0
                             and (self.pushers[i].point.x, self.pushers[i].point.y) == start),
                            None)

            assert self.ros.spin_until(lambda: first_of_scene() is not None, 10.0)
            del self.pushers[:first_of_scene()]
        return future.result()


@pytest.fixture(scope="module")
def sim(ros, log_dir):
    started = Processes(log_dir, DOMAIN_ID)
    process, log = started.start("sim_bridge.sim_node", "sim_node", seed=SEED, mode="lockstep")
    link = SimLink(ros, process, log)
    subscriptions = [s for s in ros.node.subscriptions]
    discovered = ros.spin_until(
        lambda: link.setpoint_pub.get_subscription_count() >= 1
        and all(s.get_publisher_count() >= 1 for s in subscriptions)
        and link.reset_client.service_is_ready() and link.params.services_are_ready()
        and all((link.pushers, link.keypoints, link.poses, link.scores)))
    if not discovered:
        started.stop_all()
        pytest.fail(f"sim_node not discovered; its log:\n{log.read_text()}")
    yield link
    started.stop_all()


# --------------------------------------------------------------------------- sim_node


def test_sim_lockstep_one_observation_per_setpoint(ros, sim):
    first = sim.latest()
    expected = PushTSim()
    expected.reset(SEED)
    assert stamp_ns(first.header.stamp) == 0 and first.header.frame_id == FRAME_ID
    assert (first.point.x, first.point.y) == tuple(seeded_state(SEED)[:2])
    keypoints = sim.keypoints[-1]
    assert stamp_ns(keypoints.header.stamp) == 0
    assert np.allclose([(p.x, p.y) for p in keypoints.polygon.points], expected.keypoints(),
                       atol=1e-3)  # Point32 is float32

    before = sim.stamps()
    targets = [(first.point.x + 30.0 * (i + 1), first.point.y - 20.0 * (i + 1)) for i in range(5)]
    for target in targets:  # each answers the observation in force, whose stamp it carries
        sim.send(*target)
        sim.wait_new_stamps(sim.stamps(), 1)
    sim.send(*targets[-1], stamp=first.header.stamp)  # a stale duplicate: dropped
    new = sim.stamps()[len(before):]
    ros.spin_for(0.3)
    assert sim.stamps()[len(before):] == new == [step_ns(k) for k in range(1, 6)]

    positions = {stamp_ns(m.header.stamp): (m.point.x, m.point.y) for m in sim.pushers}
    previous = np.array([first.point.x, first.point.y])
    for k, target in enumerate(targets, start=1):
        state = expected.step(target)
        now = np.array(positions[step_ns(k)])
        assert tuple(now) == tuple(state[:2])  # same simulator, bit for bit
        assert np.linalg.norm(now - target) < np.linalg.norm(previous - target)
        previous = now
    pose_stamps = {stamp_ns(m.header.stamp) for m in sim.poses}
    keypoint_stamps = {stamp_ns(m.header.stamp) for m in sim.keypoints}
    assert set(new) <= pose_stamps and set(new) <= keypoint_stamps
    assert all(0.0 <= m.data <= 1.0 for m in sim.scores)


def test_sim_refuses_malformed_setpoint_and_keeps_going(ros, sim):
    before = sim.stamps()
    sim.send(math.nan, 100.0)
    sim.send(float("inf"), 100.0)
    sim.send(1e9, 100.0)
    sim.send(200.0, 200.0)
    new = sim.wait_new_stamps(before, 1)
    ros.spin_for(0.3)
    assert len(sim.stamps()) == len(before) + 1
    assert new[0] == before[-1] + step_ns(1)
    assert sim.process.poll() is None
    log = sim.log.read_text()
    assert "not finite" in log and "outside" in log and "Traceback" not in log


def test_sim_reset_to_seed_parameter(ros, sim):
    seed = SEED + 7
    response = sim.reset(seed)
    assert response.success and str(seed) in response.message
    first = sim.pushers[0]
    assert stamp_ns(first.header.stamp) == 0
    assert (first.point.x, first.point.y) == tuple(seeded_state(seed)[:2])
    assert sim.stamps() == [0]

    refused = sim.reset(-1)  # a seed the simulator refuses: answered, not fatal
    assert not refused.success and "seed" in refused.message
    assert sim.process.poll() is None
    assert sim.reset(SEED).success  # back to the scene the other tests expect


def test_sim_without_autostart_waits_for_reset(ros, processes):
    """A second sim, renamed and remapped so it does not meet the first one."""
    topics = ("/pusht/pusher", "/pusht/keypoints", "/pusht/block_pose", "/pusht/score",
              "/pusht/setpoint", "/pusht/reset")
    remap = {"__node": "sim_b", **{name: name.replace("/pusht/", "/b/") for name in topics}}
    _, log = processes.start("sim_bridge.sim_node", "sim_b", remap=remap,
                             seed=SEED + 3, autostart=False)
    received: list[PointStamped] = []
    ros.node.create_subscription(PointStamped, "/b/pusher", received.append,
                                 qos_profile(TOPICS["pusher"]))
    client = ros.node.create_client(Trigger, "/b/reset")
    assert ros.spin_until(client.service_is_ready), log.read_text()
    ros.spin_for(0.8)  # longer than the lockstep re-send period: still nothing
    assert received == []
    future = client.call_async(Trigger.Request())
    assert ros.spin_until(future.done, 10.0) and future.result().success
    assert ros.spin_until(lambda: len(received) > 0, 10.0)
    assert stamp_ns(received[0].header.stamp) == 0
    assert (received[0].point.x, received[0].point.y) == tuple(seeded_state(SEED + 3)[:2])


# --------------------------------------------------------------------------- zone_publisher


def test_zone_publisher_latched_scenario_and_moving_zone(ros, sim, processes):
    scenarios = load_scenarios()
    processes.start("constrained_diffusion_ros.nodes.zone_publisher", "zones_static",
                    scenario="two_zones", first_id=5, rate_hz=0.0)
    processes.start("constrained_diffusion_ros.nodes.zone_publisher", "zones_moving",
                    scenario="moving_hand", first_id=20, rate_hz=0.0, follow_sim_time=True)
    bad, bad_log = processes.start("constrained_diffusion_ros.nodes.zone_publisher", "zones_bad",
                                   polygon="0,0;10,10;20,20")
    topic = TOPICS["zones"].name
    # Both publishers exist (and have published: they do so on creation) before we subscribe.
    assert ros.spin_until(lambda: ros.node.count_publishers(topic) >= 2)
    zones = ros.inbox("zones", PolygonInstanceStamped)
    assert ros.spin_until(lambda: {5, 6} <= {m.polygon.id for m in zones})
    static = {m.polygon.id: m for m in zones if m.polygon.id in (5, 6)}
    for zone_id, polygon in zip((5, 6), scenarios["two_zones"].polygons):
        assert static[zone_id].header.frame_id == FRAME_ID
        points = [(p.x, p.y) for p in static[zone_id].polygon.polygon.points]
        assert np.allclose(points, polygon)

    # The moving zone follows the sim's step: step it and read the zone for that step.
    moving = scenarios["moving_hand"]
    latest = stamp_ns(sim.latest().header.stamp)
    assert ros.spin_until(lambda: any(
        m.polygon.id == 20 and stamp_ns(m.header.stamp) == latest for m in zones)), \
        "moving zone never followed the sim"
    before = sim.stamps()
    for _ in range(3):
        sim.send(256.0, 256.0)
        sim.wait_new_stamps(sim.stamps(), 1)
    last = sim.stamps()[len(before):][-1]
    assert ros.spin_until(lambda: any(
        m.polygon.id == 20 and stamp_ns(m.header.stamp) == last for m in zones))
    message = next(m for m in zones if m.polygon.id == 20 and stamp_ns(m.header.stamp) == last)
    points = [(p.x, p.y) for p in message.polygon.polygon.points]
    assert np.allclose(points, moving.polygons_at(last // step_ns(1))[0], atol=1e-3)
    assert not np.allclose(points, moving.polygons_at(0)[0], atol=1e-3)

    assert bad.wait(timeout=20) != 0
    log = bad_log.read_text()
    assert "collinear" in log and "Traceback" not in log


# --------------------------------------------------------------------------- recorder


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
    recorder, log = processes.start("constrained_diffusion_ros.nodes.recorder", "recorder",
                                    output=bag, metadata_file=metadata_file)
    published = {"plan": PathMsg, "policy_status": DiagnosticStatus,
                 "zone_markers": MarkerArray, "zones": PolygonInstanceStamped}
    publishers = {topic: ros.publisher(topic, msg_type) for topic, msg_type in published.items()}

    def recorder_matched_all() -> bool:
        text = log.read_text()
        return all(f"{e.name}: 1 publisher(s) matched" in text for e in TOPICS.values()) \
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
        publishers["policy_status"].publish(DiagnosticStatus(name="policy", message=str(i)))
        publishers["zone_markers"].publish(MarkerArray())
        zone = PolygonInstanceStamped()
        zone.polygon.id = 40 + i
        publishers["zones"].publish(zone)
    ros.spin_for(0.2)  # let the last messages reach the recorder; it drains its queue on stop
    metadata_file.write_text(json.dumps({"scenario": "two_zones", "result": {"score": 0.5}}))
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(timeout=15) == 0, log.read_text()

    counts, messages, connections = _bag_counts(bag)
    assert (bag / "bag.mcap").is_file()
    # Publishers keep their history (transient local) and the recorder asks for it, so the bag
    # holds every setpoint this session published, from before the recorder started too.
    assert counts["/pusht/setpoint"] == sim.sent
    for topic in published:
        assert counts.get(TOPICS[topic].name) == 2, topic
    for topic in ("/pusht/pusher", "/pusht/keypoints", "/pusht/block_pose"):
        recorded = [stamp_ns(m.header.stamp) for m in messages[topic]]
        recorded = recorded[len(recorded) - recorded[::-1].index(0):]  # since the last reset
        assert set(new) <= set(recorded), topic
        assert all(recorded.count(s) == 1 for s in new[:-1]), topic  # no step recorded twice
    assert counts["/pusht/score"] >= 3
    assert sorted(m.polygon.id for m in messages["/pusht/zones"]) == [40, 41]
    by_name = {endpoint.name: endpoint for endpoint in TOPICS.values()}
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
    recorder, log = processes.start("constrained_diffusion_ros.nodes.recorder", "recorder_exists",
                                    output=tmp_path / "bag")
    assert recorder.wait(timeout=20) != 0
    text = log.read_text()
    assert "exists" in text and "Traceback" not in text
