"""The policy node's inputs on its executor, in this process: a paced zone batch leaves the
executor to the observations, the observations are the newest state only, and one answered
late is said."""

from __future__ import annotations

import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import serialize_message
from ros_helpers import observation_messages

from constrained_diffusion_ros.nodes import zone_ingest
from constrained_diffusion_ros.nodes.observation_input import ObservationInput
from constrained_diffusion_ros.nodes.policy_status import StatusReporter
from constrained_diffusion_ros.nodes.zone_ingest import ZoneIngest
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.grid import MaskCaps
from constrained_diffusion_ros.zones.live import LiveZones
from msg_schemas import FRAME_ID
from msg_schemas.capped import read_capped
from msg_schemas.conversions import stamp_seconds, zone_message

WORKSPACE = (0.0, 0.0, 512.0, 512.0)
SQUARE = np.array([(100.0, 100.0), (140.0, 100.0), (140.0, 140.0), (100.0, 140.0)])


def test_a_zone_batch_due_later_waits_on_a_timer_not_in_the_callback(ros) -> None:
    """Realtime pacing: a batch that comes before the last one's pace is over is taken and
    left for a timer, so the callback returns at once and the executor answers observations
    meanwhile; the timer applies it, stamped with when it came."""
    node = rclpy.create_node("ingest_under_test", context=ros.context)
    node.declare_parameter("zone_lifetime", 0.0)
    node.declare_parameter("keepout_threshold", 65)
    zones, changes = LiveZones(workspace=WORKSPACE), []
    ingest = ZoneIngest(node, zones, WORKSPACE, MaskCaps(),
                        lambda received, _within: changes.append((received, time.monotonic())),
                        realtime=True)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(node)
    try:
        due = ingest._paced_until = time.monotonic() + 0.3  # the last batch took 0.3 s
        came = time.monotonic()
        ingest._on_zone(serialize_message(zone_message(7, SQUARE, node.get_clock().now()
                                                       .to_msg())),
                        {"source_timestamp": 1, "publication_sequence_number": 1})
        assert zones.ids == [] and changes == []  # not applied in the callback
        deadline = time.monotonic() + 5.0
        while not changes and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert zones.ids == [7]
        received, applied = changes[0]
        assert received >= came and applied >= due - 0.01  # when it came; applied when due
    finally:
        ingest.shutdown()
        executor.shutdown()
        node.destroy_node()


def test_a_zone_batch_reads_the_newest_message_per_id_and_falls_back_on_a_refused_one(
        ros, monkeypatch) -> None:
    """A flood of 300 messages for 3 ids costs 3 reads, and each id takes its last message.
    A newest message that is refused (a wrong frame; bytes after the message that make its
    last 8 read as another id) leaves the one before it of that id to be read, as if the
    refused one had not come."""
    node = rclpy.create_node("batch_under_test", context=ros.context)
    node.declare_parameter("zone_lifetime", 0.0)
    node.declare_parameter("keepout_threshold", 65)
    zones = LiveZones(workspace=WORKSPACE)
    ingest = ZoneIngest(node, zones, WORKSPACE, MaskCaps(), lambda *_: None, realtime=False)
    reads = []

    def counted(*args):
        reads.append(args[0])
        return read_capped(*args)

    monkeypatch.setattr(zone_ingest, "read_capped", counted)
    stamp = node.get_clock().now().to_msg()

    def message(zone_id: int, shift: float, frame_id: str = FRAME_ID) -> bytes:
        msg = zone_message(zone_id, SQUARE + shift, stamp)
        msg.header.frame_id = frame_id
        return serialize_message(msg)

    flood = [message(1 + k % 3, k) for k in range(300)]
    lying = message(5, 50.0) + (6).to_bytes(8, "little", signed=True)
    batch = [*flood, message(4, 10.0), message(4, 20.0, "elsewhere"), message(6, 30.0), lying]
    try:
        for k, data in enumerate(batch):  # taken at once: the callback's own and those waiting
            ingest._deferred.append((data, {"source_timestamp": k + 1,
                                            "publication_sequence_number": k + 1}))
        ingest._on_zone(batch[-1], {"source_timestamp": len(batch),
                                    "publication_sequence_number": len(batch)})
        outlines = zones.outlines()
        assert sorted(outlines) == [1, 2, 3, 4, 6]
        for zone_id, last in ((1, 297), (2, 298), (3, 299), (4, 10), (6, 30)):
            assert np.allclose(outlines[zone_id][:4], SQUARE + last), zone_id
        assert len(reads) == 3 + 2 + 2  # the last per id, and the one before each refused one
        assert ingest.counts["zone_messages"] == len(batch)
        assert ingest.counts["zones_refused"] == 2
    finally:
        ingest.shutdown()
        node.destroy_node()


def test_observations_keep_the_newest_state_only(ros) -> None:
    """Each observation half is subscribed with a queue of one: a node held a while (a zone
    flood) answers the state as it is, not a backlog of old ones."""
    node = rclpy.create_node("observer_under_test", context=ros.context)
    try:
        observations = ObservationInput(node, PUSHT_ROBOT, lambda stamp, msg: None)
        depths = [s.qos_profile.depth for s in observations.subscriptions]
        assert depths == [1, 1]
    finally:
        node.destroy_node()


def test_an_observation_answered_a_period_after_it_was_published_is_counted_late(ros) -> None:
    """Realtime: the shield answers a state at most a control period old; an observation
    whose pusher half was published longer ago than that when it is taken is counted late
    (WARN on /diagnostics), one taken at once is not."""
    node = rclpy.create_node("late_observer_under_test", context=ros.context)
    try:
        observations = ObservationInput(node, PUSHT_ROBOT, lambda stamp, msg: None,
                                        late_s=0.1)
        for step, age_s in ((1, 0.0), (2, 0.5)):
            keypoints, pusher = observation_messages(step, (100.0, 100.0))
            observations._on_keypoints(keypoints, {})
            observations._on_pusher(pusher, {"source_timestamp":
                                             int((time.time() - age_s) * 1e9)})
            assert observations.take(stamp_seconds(pusher.header.stamp)) is not None
            status = observations.status()
            assert int(status["observations_late"]) == (step == 2)
        assert int(status["observations_taken"]) == 2
        assert float(status["observation_age_ms"]) >= 500
        reporter = StatusReporter(node)
        assert reporter.health({"observations_late": 0})[0] == DiagnosticStatus.OK
        level, message = reporter.health(status)
        assert level == DiagnosticStatus.WARN and "1 observation(s) answered more" in message
        assert reporter.health(status)[0] == DiagnosticStatus.OK  # said once, as it rose
    finally:
        node.destroy_node()
