"""A realtime policy node driven by the test itself: observations, zones and masks go in,
setpoints (with their arrival time), plans and statuses come out. Shared by the tests of hostile
inputs, of failing safe and of resets.

The node runs on a tick of `period_s` (long by default, so "within one tick" is measured against
a period much longer than anything the node needs). The tiny policy's setpoints are noise-like,
so a zone dropped on the latest one is a real test of the reaction.
"""

from __future__ import annotations

import time

import numpy as np
import shapely
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point32, PointStamped, PolygonInstanceStamped, PolygonStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from ros_helpers import observation_messages, step_stamp

from msg_schemas import FRAME_ID, TOPICS
from msg_schemas.conversions import stamp_seconds
from sim_bridge import AGENT_RADIUS

TICK_S = 1.0
PUSHER = (40.0, 470.0)


def status_values(report: DiagnosticArray) -> dict[str, str]:
    return {kv.key: kv.value for kv in report.status[0].values}


class RealtimeLink:
    """Starts `node` (an executable of the launcher) in realtime at 1 / `period_s` Hz with the
    tiny policy and `fast_safe`, and `parameters` besides."""

    def __init__(self, ros, processes, tiny_model, configurations_file, period_s: float = TICK_S,
                 node: str = "policy_node", **parameters: object) -> None:
        self.ros, self.processes, self.period_s = ros, processes, period_s
        self.arrivals: list[tuple[float, np.ndarray]] = []
        ros.inbox("setpoint", PointStamped, lambda m: self.arrivals.append(
            (time.monotonic(), np.array([m.point.x, m.point.y]))))
        self.statuses = ros.inbox("diagnostics", DiagnosticArray)
        self.plans = ros.inbox("plan", PathMsg)
        self.zones = ros.publisher("zones", PolygonInstanceStamped)
        self.masks = ros.publisher("keepout_mask", OccupancyGrid)
        self.keypoints = ros.publisher("keypoints", PolygonStamped)
        self.pusher = ros.publisher("pusher", PointStamped)
        self.process, self.log = processes.start(
            "policy_node", node=node, model=tiny_model, configurations_file=configurations_file,
            **{"configuration": "fast_safe", "mode": "realtime", "rate_hz": 1 / period_s,
               **parameters})
        self.step = 0
        assert ros.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in (
            self.zones, self.masks, self.keypoints, self.pusher))
            and ros.node.count_publishers(TOPICS["setpoint"].name) >= 1), processes.logs()

    def observe(self, pusher: tuple[float, float] = PUSHER) -> None:
        keypoints, message = observation_messages(self.step, pusher)
        self.keypoints.publish(keypoints)
        self.pusher.publish(message)
        self.step += 1

    def observe_handled(self, pusher: tuple[float, float] = PUSHER) -> None:
        """An observation, and a wait until the node says it took or refused it: it keeps each
        half's newest message only, so one published before it handled the last would replace
        that one, as a robot's newer state does."""
        stamp = stamp_seconds(step_stamp(self.step))
        self.observe(pusher)
        self.latest_status(lambda v: abs(float(v.get("observation_stamp", "nan")) - stamp)
                           < 1e-6)

    def planning(self) -> None:
        """Observations until a plan is in and a tick has sent one of its waypoints."""
        while not self.plans:
            self.observe()
            self.ros.spin_until(lambda: bool(self.plans), 0.5)
        ticks = len(self.arrivals)
        assert self.ros.spin_until(lambda: len(self.arrivals) > ticks, 2 * self.period_s + 5)

    def drop_zone_on_setpoint(self, zone_id: int) -> tuple[float, shapely.Geometry]:
        """A 30 px square zone on the latest setpoint; (when it was sent, the zone grown by
        the pusher radius less half a px)."""
        x, y = self.arrivals[-1][1]
        zone = ((x - 15, y - 15), (x + 15, y - 15), (x + 15, y + 15), (x - 15, y + 15))
        msg = PolygonInstanceStamped()
        msg.header.frame_id, msg.polygon.id = FRAME_ID, zone_id
        msg.polygon.polygon.points = [Point32(x=float(a), y=float(b), z=0.0) for a, b in zone]
        sent = time.monotonic()
        self.zones.publish(msg)
        return sent, shapely.Polygon(zone).buffer(AGENT_RADIUS - 0.5)

    def first_outside(self, after: float, grown: shapely.Geometry, timeout: float) -> float:
        """When the first setpoint outside `grown` arrived after `after` (AssertionError if
        none came within `timeout`)."""
        def outside() -> list[float]:
            return [t for t, p in self.arrivals
                    if t > after and not grown.contains(shapely.Point(*p))]
        assert self.ros.spin_until(lambda: bool(outside()), timeout), self.processes.logs()
        return outside()[0]

    def latest_status(self, predicate, timeout: float = 10.0) -> dict[str, str]:
        assert self.ros.spin_until(lambda: self.statuses and predicate(
            status_values(self.statuses[-1])), timeout), self.processes.logs()
        return status_values(self.statuses[-1])

    def exited_by(self, deadline: float) -> bool:
        """Whether the node's process has exited by the time.monotonic() `deadline`."""
        while self.process.poll() is None and time.monotonic() < deadline:
            self.ros.spin_until(lambda: False, 0.02)
        return self.process.poll() is not None
