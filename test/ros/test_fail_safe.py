"""The realtime policy node fails safe, over real DDS: an executor that dies or stalls (it
answers zones) does not leave the control clock commanding the robot alone; a zone message too
big to read is refused before it is read; the filter cannot be weakened by a parameter call.

Faults are injected from outside the package (`faulty_policy_node.py`). The test feeds
observations itself (`realtime_link.py`), at 20 Hz: a clock that went on alone would send many
setpoints in a second.
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
from geometry_msgs.msg import Point32, PolygonInstanceStamped, PolygonStamped
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message, serialize_message
from realtime_link import RealtimeLink
from ros_helpers import step_stamp

from constrained_diffusion_ros.evaluation import launcher
from msg_schemas import FRAME_ID
from node_support.spin import SHUTDOWN_DEADLINE_S

PERIOD_S = 0.05  # 20 Hz: a clock that went on alone would send many setpoints in a second
# A zone answered after a message too big to read: was 8000 ms. Typically 6-35 ms here; a CI
# run under full load once took 341 ms, so the bound says "not seconds", not a timing.
REACTION_BOUND_MS = 1000.0


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


def realtime_node(ros, processes, tiny_model, configurations_file, node: str = "policy_node",
                  **parameters: object) -> RealtimeLink:
    """A realtime node at 20 Hz with setpoints flowing, without the zones that earlier tests'
    latched publishers would hand it."""
    for publisher in list(ros.node.publishers):
        if publisher.topic_name == "/pusht/zones":
            ros.node.destroy_publisher(publisher)
    started = RealtimeLink(ros, processes, tiny_model, configurations_file, PERIOD_S, node,
                           **parameters)
    started.planning()
    return started


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
    link = realtime_node(ros, processes, tiny_model, configurations_file, faulty("raise", 41))
    said: list[float] = []  # when the ERROR that the node stopped arrived
    ros.inbox("diagnostics", DiagnosticArray, lambda m: said.append(time.monotonic()) if (
        m.status[0].level == DiagnosticStatus.ERROR
        and "stopped commanding the robot" in m.status[0].message) else None)
    sent = time.monotonic()
    link.zones.publish(zone_bytes(41, 4))  # the executor dies taking it
    # Within a second of its death (slack here for the zone's delivery on a busy machine).
    assert link.exited_by(sent + 3.0), "the node still runs 3 s after its executor died"
    assert link.process.returncode == 1
    ros.spin_until(lambda: False, 0.5)  # whatever was still in flight arrives
    assert said, [s.status[0].message for s in link.statuses[-3:]]
    # The setpoints stop before the ERROR goes out: none after it but one in flight.
    late = [t - said[0] for t, _ in link.arrivals if t > said[0] + PERIOD_S]
    assert late == [], f"setpoints {late} s after the node said it stopped"
    log = link.log.read_text()
    assert "executor died: RuntimeError" in log and "Traceback" not in log, log


def test_a_stalled_executor_withholds_setpoints_and_sigint_stops_the_node(
        ros, processes, tiny_model, configurations_file, faulty) -> None:
    """The executor stops answering (a zone callback that never returns): the clock sends no
    setpoint once `executor_watchdog_s` has passed, and Ctrl-C still ends the node."""
    link = realtime_node(ros, processes, tiny_model, configurations_file, faulty("stall", 42),
                         executor_watchdog_s=0.3)
    sent = time.monotonic()
    link.zones.publish(zone_bytes(42, 4))  # the executor blocks taking it
    ros.spin_until(lambda: False, 2.5)
    # The watchdog's 0.3 s, and a second's slack for the zone's delivery on a busy machine; a
    # clock going on alone sends 20 a second.
    late = [t - sent for t, _ in link.arrivals if t > sent + 0.3 + 1.0]
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
    link = realtime_node(ros, processes, tiny_model, configurations_file)
    link.zones.publish(zone_bytes(2, 1_000_000))
    sent, grown = link.drop_zone_on_setpoint(3)
    first_safe = link.first_outside(sent, grown, 2.0)
    assert first_safe - sent < 1.0, first_safe - sent  # was 8 s
    status = link.latest_status(lambda v: "3" in v["zone_ids"].split(","))
    # In the node, from taking the zone: the behaviour, not a timing (it was seconds, and a
    # loaded CI machine may take a tick or two; docs/hostile_inputs.md has the figures).
    assert float(status["zone_to_setpoint_ms"]) < REACTION_BOUND_MS
    assert status["zones_oversized"] == "1" and "2" not in status["zone_ids"].split(",")
    assert "bytes, more than the" in status["zone_refusal"]
    assert ros.spin_until(lambda: sum(t > first_safe for t, _ in link.arrivals) >= 3, 5.0)
    after = [p for t, p in link.arrivals if t > first_safe]
    assert not any(grown.contains(shapely.Point(*p)) for p in after)


def set_parameter(ros, name: str, value: object) -> tuple[bool, str]:
    client = ros.node.create_client(SetParameters, "/pusht/policy_node/set_parameters")
    assert client.wait_for_service(timeout_sec=20)
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter(name, value=value).to_parameter_msg()]))
    assert ros.spin_until(future.done, 20)
    result = future.result().results[0]
    return result.successful, result.reason


@pytest.mark.parametrize("allow", [False, True], ids=["refused", "allowed_at_start"])
def test_a_configuration_that_promises_less_is_refused_at_run_time(
        ros, processes, tiny_model, configurations_file, allow: bool) -> None:
    """`configuration:=ddim10_none` from any participant turned the shield off, and the status
    went back to OK. Now a weaker one is refused unless the node was started to allow it, and a
    change shows in /diagnostics."""
    link = realtime_node(ros, processes, tiny_model, configurations_file,
                         allow_weaker_configuration=allow)
    for weaker in ("fast_project", "fast_none"):  # guarantee "setpoint", then "none"
        ok, reason = set_parameter(ros, "configuration", weaker)
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
    ok, reason = set_parameter(ros, "configuration", "fast_safe")  # as strong: always allowed
    assert ok, reason
    # Settings that let more through: every zone expiring as it comes, fewer keep-out cells.
    for name, value in (("zone_lifetime", 1e-6), ("keepout_threshold", 100)):
        ok, reason = set_parameter(ros, name, value)
        assert ok == allow, reason
    if not allow:
        status = link.latest_status(lambda v: v["changes_refused"] == "4")
        assert any("refused (they would weaken the filter)" in s.status[0].message
                   for s in link.statuses)


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
    link = realtime_node(ros, processes, tiny_model, configurations_file)
    link.keypoints.publish(keypoints_bytes(link.step, 1_000_000))
    sent, grown = link.drop_zone_on_setpoint(4)
    link.first_outside(sent, grown, 2.0)
    status = link.latest_status(lambda v: int(v["observations_refused"]) >= 1)
    assert float(status["zone_to_setpoint_ms"]) < REACTION_BOUND_MS
    assert "refused unread" in link.log.read_text()
