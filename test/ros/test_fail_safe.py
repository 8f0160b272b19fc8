"""The realtime policy node fails safe, over real DDS: an executor that dies or stalls (it
answers zones) does not leave the control clock commanding the robot alone; a zone message too
big to read is refused before it is read; the filter cannot be weakened by a parameter call.

Faults are injected from outside the package (`faulty_policy_node.py`). The test feeds
observations itself, as in `test_hostile_inputs.py`.
"""

from __future__ import annotations

import signal
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import shapely
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point32, PointStamped, PolygonInstanceStamped, PolygonStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message, serialize_message
from ros_helpers import step_stamp

from constrained_diffusion_ros.evaluation import launcher
from msg_schemas import FRAME_ID, TOPICS
from msg_schemas.spin import SHUTDOWN_DEADLINE_S
from sim_bridge import AGENT_RADIUS

PERIOD_S = 0.05  # 20 Hz: a clock that went on alone would send many setpoints in a second
PUSHER = (40.0, 470.0)
REACTION_BOUND_MS = 300.0  # a zone answered after a message too big to read: was 8000 ms


def status_values(report: DiagnosticArray) -> dict[str, str]:
    return {kv.key: kv.value for kv in report.status[0].values}


def zone_bytes(zone_id: int, vertices: int) -> bytes:
    """A serialized zone message of `vertices` vertices (a ring about the centre), built
    without a Point32 object each. Little-endian CDR: the header, the vertex count and the
    vertices, then the id (int64, 8-aligned from the end of the 4-byte encapsulation)."""
    message = PolygonInstanceStamped()
    message.header.frame_id, message.polygon.id = FRAME_ID, zone_id
    message.polygon.polygon.points = [Point32()]
    one = serialize_message(message)
    head = one[:-(4 + 12 + 8)]  # a single vertex leaves no padding before the id
    ring = np.zeros((vertices, 3), np.float32)
    angles = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
    ring[:, 0], ring[:, 1] = 256 + 100 * np.cos(angles), 256 + 100 * np.sin(angles)
    body = head + struct.pack("<I", vertices) + ring.tobytes()
    return body + bytes(-(len(body) - 4) % 8) + struct.pack("<q", zone_id)


def test_zone_bytes_are_the_zone_message() -> None:
    for vertices in (3, 4, 5):
        message = deserialize_message(zone_bytes(7, vertices), PolygonInstanceStamped)
        assert message.polygon.id == 7 and message.header.frame_id == FRAME_ID
        assert len(message.polygon.polygon.points) == vertices
        assert message.polygon.polygon.points[0].x == pytest.approx(356.0)


class Link:
    """A realtime policy node (`node`: an executable of the launcher) fed by the test."""

    def __init__(self, ros, processes, tiny_model, configurations_file, node: str = "policy_node",
                 **parameters) -> None:
        self.ros, self.processes = ros, processes
        self.arrivals: list[tuple[float, np.ndarray]] = []
        ros.inbox("setpoint", PointStamped, lambda m: self.arrivals.append(
            (time.monotonic(), np.array([m.point.x, m.point.y]))))
        self.statuses = ros.inbox("diagnostics", DiagnosticArray)
        self.plans = ros.inbox("plan", PathMsg)
        self.zones = ros.publisher("zones", PolygonInstanceStamped)
        self.keypoints = ros.publisher("keypoints", PolygonStamped)
        self.pusher = ros.publisher("pusher", PointStamped)
        self.process, self.log = processes.start(
            "policy_node", node=node, model=tiny_model, configurations_file=configurations_file,
            configuration="fast_safe", mode="realtime", rate_hz=1 / PERIOD_S, **parameters)
        self.step = 0
        # Zones latched by an earlier test's publishers reach this node too: gone with them.
        for publisher in list(ros.node.publishers):
            if publisher.topic_name == self.zones.topic_name and publisher is not self.zones:
                ros.node.destroy_publisher(publisher)
        assert ros.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in (
            self.zones, self.keypoints, self.pusher))
            and ros.node.count_publishers(TOPICS["setpoint"].name) >= 1), processes.logs()

    def observe(self) -> None:
        keypoints = PolygonStamped()
        keypoints.header.stamp, keypoints.header.frame_id = step_stamp(self.step), FRAME_ID
        keypoints.polygon.points = [Point32(x=256.0, y=256.0 + i, z=0.0) for i in range(9)]
        message = PointStamped()
        message.header = keypoints.header
        message.point.x, message.point.y = PUSHER
        self.keypoints.publish(keypoints)
        self.pusher.publish(message)
        self.step += 1

    def running(self) -> None:
        """Observations until a plan is in and setpoints come every tick."""
        while not self.plans:
            self.observe()
            self.ros.spin_until(lambda: bool(self.plans), 0.5)
        count = len(self.arrivals)
        assert self.ros.spin_until(lambda: len(self.arrivals) > count + 3, 10), \
            self.processes.logs()

    def zone_on_setpoint(self, zone_id: int) -> tuple[float, shapely.Geometry]:
        """A 30 px square on the latest setpoint: (when it was sent, the zone grown by the
        pusher radius less half a px)."""
        x, y = self.arrivals[-1][1]
        zone = ((x - 15, y - 15), (x + 15, y - 15), (x + 15, y + 15), (x - 15, y + 15))
        msg = PolygonInstanceStamped()
        msg.header.frame_id, msg.polygon.id = FRAME_ID, zone_id
        msg.polygon.polygon.points = [Point32(x=float(a), y=float(b), z=0.0) for a, b in zone]
        sent = time.monotonic()
        self.zones.publish(msg)
        return sent, shapely.Polygon(zone).buffer(AGENT_RADIUS - 0.5)

    def exited_by(self, deadline: float) -> bool:
        while self.process.poll() is None and time.monotonic() < deadline:
            self.ros.spin_until(lambda: False, 0.02)
        return self.process.poll() is not None

    def latest_status(self, predicate, timeout: float = 10.0) -> dict[str, str]:
        assert self.ros.spin_until(lambda: self.statuses and predicate(
            status_values(self.statuses[-1])), timeout), self.processes.logs()
        return status_values(self.statuses[-1])


@pytest.fixture
def faulty(monkeypatch):
    """Starts `faulty_policy_node` with FAULT=<fault> through the package's launcher."""
    monkeypatch.setitem(launcher.NODES, "faulty_policy_node", "faulty_policy_node")
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))

    def use(fault: str, zone_id: int) -> str:
        monkeypatch.setenv("FAULT", fault)
        monkeypatch.setenv("FAULT_ZONE", str(zone_id))
        return "faulty_policy_node"
    return use


def test_an_executor_that_dies_sends_no_setpoint_after_says_error_and_exits_nonzero(
        ros, processes, tiny_model, configurations_file, faulty) -> None:
    """Before: the executor died, the clock thread went on publishing setpoints with no zone
    handling, /diagnostics stopped at OK, and SIGINT was ignored."""
    link = Link(ros, processes, tiny_model, configurations_file, faulty("raise", 41))
    link.running()
    sent = time.monotonic()
    link.zones.publish(zone_bytes(41, 4))  # the executor dies taking it
    assert link.exited_by(sent + 1.5), "the node still runs 1.5 s after its executor died"
    died = time.monotonic()
    assert link.process.returncode == 1
    ros.spin_until(lambda: False, 0.5)  # whatever was still in flight arrives
    late = [t - sent for t, _ in link.arrivals if t > sent + 2 * PERIOD_S]
    assert late == [], f"setpoints {late} s after the executor died (exit at {died - sent} s)"
    errors = [s.status[0] for s in link.statuses if s.status[0].level == DiagnosticStatus.ERROR]
    assert errors and "stopped commanding the robot" in errors[-1].message, \
        [s.status[0].message for s in link.statuses[-3:]]
    log = link.log.read_text()
    assert "executor died: RuntimeError" in log and "Traceback" not in log, log


def test_a_stalled_executor_withholds_setpoints_and_sigint_stops_the_node(
        ros, processes, tiny_model, configurations_file, faulty) -> None:
    """The executor stops answering (a zone callback that never returns): the clock sends no
    setpoint once `executor_watchdog_s` has passed, and Ctrl-C still ends the node."""
    link = Link(ros, processes, tiny_model, configurations_file, faulty("stall", 42),
                executor_watchdog_s=0.3)
    link.running()
    sent = time.monotonic()
    link.zones.publish(zone_bytes(42, 4))  # the executor blocks taking it
    ros.spin_until(lambda: False, 1.5)
    late = [t - sent for t, _ in link.arrivals if t > sent + 0.3 + 2 * PERIOD_S]
    assert late == [], f"setpoints {late} s after the executor stalled"
    link.process.send_signal(signal.SIGINT)
    assert link.exited_by(time.monotonic() + SHUTDOWN_DEADLINE_S + 2.0), \
        "SIGINT did not end a stalled node"


def test_a_zone_too_big_to_read_is_refused_unread_and_a_zone_right_after_is_obeyed(
        ros, processes, tiny_model, configurations_file) -> None:
    """A 1M-vertex zone (12 MB) took 8 s to read, the zone published 10 ms after it waited, and
    75 setpoints went inside it. Now it is refused by its length, unread, and the zone after it
    is answered as soon as the middleware has delivered both (from one publisher, in order: the
    12 MB first, which takes DDS about 0.1 s here; docs/hostile_inputs.md)."""
    link = Link(ros, processes, tiny_model, configurations_file)
    link.running()
    link.zones.publish(zone_bytes(2, 1_000_000))
    before = len(link.arrivals)
    sent, grown = link.zone_on_setpoint(3)
    assert ros.spin_until(lambda: any(t > sent and not grown.contains(shapely.Point(*p))
                                      for t, p in link.arrivals[before:]), 2.0)
    first_safe = next(t for t, p in link.arrivals[before:]
                      if t > sent and not grown.contains(shapely.Point(*p)))
    assert first_safe - sent < 1.0, first_safe - sent  # was 8 s
    status = link.latest_status(lambda v: "3" in v["zone_ids"].split(","))
    # In the node, from taking the zone: the behaviour, not a timing (it was seconds, and a
    # loaded CI machine may take a tick or two; docs/hostile_inputs.md has the figures).
    assert float(status["zone_to_setpoint_ms"]) < REACTION_BOUND_MS
    assert status["zones_oversized"] == "1" and "2" not in status["zone_ids"].split(",")
    assert "bytes, more than the" in status["zone_refusal"]
    after = [p for t, p in link.arrivals if t > first_safe]
    assert after and not any(grown.contains(shapely.Point(*p)) for p in after)


def set_configuration(ros, name: str) -> tuple[bool, str]:
    client = ros.node.create_client(SetParameters, "/pusht/policy_node/set_parameters")
    assert client.wait_for_service(timeout_sec=20)
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter("configuration", value=name).to_parameter_msg()]))
    assert ros.spin_until(future.done, 20)
    result = future.result().results[0]
    return result.successful, result.reason


@pytest.mark.parametrize("allow", [False, True], ids=["refused", "allowed_at_start"])
def test_a_configuration_that_promises_less_is_refused_at_run_time(
        ros, processes, tiny_model, configurations_file, allow: bool) -> None:
    """`configuration:=ddim10_none` from any participant turned the shield off, and the status
    went back to OK. Now a weaker one is refused unless the node was started to allow it, and a
    change shows in /diagnostics."""
    link = Link(ros, processes, tiny_model, configurations_file,
                allow_weaker_configuration=allow)
    link.running()
    for weaker in ("fast_project", "fast_none"):  # guarantee "setpoint", then "none"
        ok, reason = set_configuration(ros, weaker)
        assert ok == allow, reason
        if not allow:
            assert "promises less" in reason and "allow_weaker_configuration" in reason
    status = link.latest_status(lambda v: v["configuration_changes"] == ("2" if allow else "0"))
    assert status["configuration"] == ("fast_none" if allow else "fast_safe")
    assert status["guarantee"] == ("none" if allow else "body")
    if allow:
        changed = [s.status[0] for s in link.statuses
                   if "configuration changed" in s.status[0].message]
        assert changed and changed[-1].level == DiagnosticStatus.WARN
    ok, reason = set_configuration(ros, "fast_safe")  # as strong or stronger: always allowed
    assert ok, reason


def keypoints_bytes(step: int, points: int) -> bytes:
    """Serialized keypoints (PolygonStamped, the points last) of `points` points."""
    message = PolygonStamped()
    message.header.stamp, message.header.frame_id = step_stamp(step), FRAME_ID
    message.polygon.points = [Point32()]
    head = serialize_message(message)[:-(4 + 12)]
    return head + struct.pack("<I", points) + bytes(12 * points)


def test_keypoints_too_big_to_read_are_refused_unread_and_a_zone_after_is_obeyed(
        ros, processes, tiny_model, configurations_file) -> None:
    """Observations come from any participant too: a million keypoints would have held the
    executor for seconds while rclpy read them."""
    link = Link(ros, processes, tiny_model, configurations_file)
    link.running()
    link.keypoints.publish(keypoints_bytes(link.step, 1_000_000))
    before = len(link.arrivals)
    sent, grown = link.zone_on_setpoint(4)
    assert ros.spin_until(lambda: any(t > sent and not grown.contains(shapely.Point(*p))
                                      for t, p in link.arrivals[before:]), 2.0)
    status = link.latest_status(lambda v: int(v["observations_refused"]) >= 1)
    assert float(status["zone_to_setpoint_ms"]) < REACTION_BOUND_MS
    assert "refused unread" in link.log.read_text()
