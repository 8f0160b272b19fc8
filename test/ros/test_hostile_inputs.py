"""Hostile and unlucky inputs to a running policy node, over real DDS: keep-out masks that cost
more than the node can hold, and pusher reports no robot can make.

The realtime node runs on a long tick (`TICK_S`, `realtime_link.py`), so a stalled executor
(the failure these tests guard against: a fine mask froze it for minutes) shows as a missed
tick. The test feeds observations itself with the pusher at `PUSHER`.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
import shapely
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Point32, PolygonInstanceStamped
from realtime_link import PUSHER, TICK_S, RealtimeLink, status_values
from ros_helpers import step_stamp

from msg_schemas import FRAME_ID
from msg_schemas.conversions import occupancy_grid
from sim_bridge import AGENT_RADIUS


def checkerboard(cells: int, rows: slice | None = None) -> np.ndarray:
    """A (cells, cells) mask of alternating keep-out cells (every cell its own piece), in
    `rows` only if given."""
    board = np.zeros((cells, cells), dtype=np.int8)
    pattern = (np.add.outer(np.arange(cells), np.arange(cells)) % 2 == 0) * 100
    board[rows or slice(None)] = pattern[rows or slice(None)]
    return board


@pytest.fixture
def link(ros, processes, tiny_model, configurations_file) -> RealtimeLink:
    return RealtimeLink(ros, processes, tiny_model, configurations_file)


@pytest.mark.parametrize("mask, resolution", [
    (checkerboard(128), 4.0),  # 8,192 pieces: froze the executor, 2 GB
    (checkerboard(256, slice(192, 256)), 2.0),  # 64 rows of it: zones ignored for 200 s
], ids=["checkerboard_128", "checkerboard_rows_256"])
def test_a_mask_too_fine_to_hold_is_refused_and_a_zone_right_after_it_is_obeyed_in_a_tick(
        link: RealtimeLink, mask: np.ndarray, resolution: float) -> None:
    link.planning()
    link.masks.publish(occupancy_grid(mask, resolution, (0.0, 0.0), step_stamp(0)))
    before = len(link.arrivals)
    sent, grown = link.drop_zone_on_setpoint(11)
    # The safe setpoint for the zone comes at once, not with the next tick: the executor was
    # not held by the mask.
    assert link.ros.spin_until(lambda: len(link.arrivals) > before, TICK_S), \
        link.processes.logs()
    reaction, safe = link.arrivals[before]
    assert reaction - sent < 0.5 * TICK_S
    assert not grown.contains(shapely.Point(*safe))
    status = link.latest_status(lambda v: v.get("masks_refused") == "1")
    assert "11" in status["zone_ids"].split(",")
    assert not any(i.startswith("keepout/") for i in status["zone_ids"].split(","))
    # Ticks keep coming from the held, safe setpoint.
    ticks = len(link.arrivals)
    assert link.ros.spin_until(lambda: len(link.arrivals) > ticks + 1, 3 * TICK_S + 2)
    assert not any(grown.contains(shapely.Point(*p)) for _, p in link.arrivals[before:])


def test_a_mask_within_the_caps_is_built_while_zones_are_answered(link: RealtimeLink) -> None:
    """Sixteen 20 px blocks: built off the executor and put in force as keepout/<k> zones."""
    link.planning()
    mask = np.zeros((128, 128), dtype=np.int8)
    for k in range(16):
        row, col = 8 * (k // 4) + 2, 8 * (k % 4) + 90
        mask[row:row + 5, col:col + 5] = 100
    link.masks.publish(occupancy_grid(mask, 4.0, (0.0, 0.0), step_stamp(0)))
    # (A mask an earlier test latched may come first: only this one is ever applied.)
    status = link.latest_status(lambda v: v.get("masks_applied") == "1")
    assert sum(i.startswith("keepout/") for i in status["zone_ids"].split(",")) == 16


def test_a_pusher_no_robot_can_be_is_refused_and_never_held_at(link: RealtimeLink) -> None:
    """With no free space the node holds the pusher where it is. A pusher reported at
    (1e6, 1e6) made that the clipped (512, 512), and at (-300, 200), (0, 200): commands to
    places the robot never was. Refused, the hold stays where the plausible pusher was."""
    link.planning()
    everything = PolygonInstanceStamped()
    everything.header.frame_id, everything.polygon.id = FRAME_ID, 13
    everything.polygon.polygon.points = [Point32(x=x, y=y, z=0.0) for x, y in (
        (-1e30, -1e30), (1e30, -1e30), (1e30, 1e30), (-1e30, 1e30))]
    link.zones.publish(everything)
    link.latest_status(lambda v: "13" in v["zone_ids"].split(","))
    link.observe()  # a plausible pusher: held where it is
    before = len(link.arrivals)
    for pusher in [(1e6, 1e6), (-300.0, 200.0)] * 3:
        link.observe_handled(pusher)
    assert link.ros.spin_until(lambda: len(link.arrivals) > before + 1, 3 * TICK_S + 2)
    sent = [p for _, p in link.arrivals[before:]]
    assert all(np.array_equal(p, PUSHER) for p in sent), sent
    status = link.latest_status(lambda v: int(v.get("observations_refused", 0)) >= 6)
    assert int(status["unsound_setpoints"]) >= 1  # the hold, reported as ERROR


def planning_child(node_pid: int) -> int:
    """The pid of the policy node's planning process (its one child)."""
    children = [int(c) for task in Path(f"/proc/{node_pid}/task").iterdir()
                for c in (task / "children").read_text().split()]
    assert len(children) == 1, children
    return children[0]


def test_a_killed_planning_process_is_restarted_and_error_stays_until_it_plans(
        link: RealtimeLink) -> None:
    """After SIGKILL of the planning child the node said ERROR once, then "running", then WARN
    for good, and never planned again. Now: ERROR in every status until a plan comes from a
    restarted child, then the restart counted and the status no longer ERROR."""
    link.planning()
    node = link.processes.processes["policy_node"].pid
    child = planning_child(node)
    os.kill(child, signal.SIGKILL)
    failed = link.latest_status(lambda v: v.get("planning_failed") == "True")
    assert link.statuses[-1].status[0].level == DiagnosticStatus.ERROR, failed
    plans = len(link.plans)
    while len(link.plans) == plans:  # observations until a plan comes from the new child
        link.observe()
        assert link.ros.spin_until(lambda: len(link.plans) > plans, 0.5) or link.step < 200, \
            link.processes.logs()
    levels_before = [s.status[0].level for s in link.statuses
                     if status_values(s).get("planning_failed") == "True"]
    assert levels_before and set(levels_before) == {DiagnosticStatus.ERROR}
    status = link.latest_status(lambda v: v.get("planning_failed") == "False")
    assert status["planning_restarts"] == "1" and planning_child(node) != child


def test_a_pusher_parked_at_a_zones_edge_is_reported_as_a_standstill(
        link: RealtimeLink) -> None:
    """The pusher reported in one place for 8 steps with a zone 2 px from its disc: the node's
    diagnostics count the standstill (5 steps or more), as the evaluation counts them."""
    link.planning()
    beside = PolygonInstanceStamped()
    beside.header.frame_id, beside.polygon.id = FRAME_ID, 14
    x = PUSHER[0] + AGENT_RADIUS + 2
    beside.polygon.polygon.points = [Point32(x=a, y=b, z=0.0) for a, b in (
        (x, 440.0), (x + 30, 440.0), (x + 30, 500.0), (x, 500.0))]
    link.zones.publish(beside)
    link.latest_status(lambda v: "14" in v["zone_ids"].split(","))
    for _ in range(8):
        link.observe_handled()
    status = link.latest_status(lambda v: int(v.get("standstill_steps", 0)) >= 5)
    assert float(status["standstill_longest_s"]) >= 0.5
