"""Observations in from ROS for the policy node: the keypoints and the pusher, paired by stamp.

`ObservationInput` is a helper in the manner of tf2_ros's `TransformListener`: built with a node,
it owns the two observation subscriptions and the halves waiting for their other half, and hands
the node each whole observation once, checked: one that is not finite, or whose pusher cannot be
the robot's (out of the workspace, or a jump no PD pusher can make), is refused with a warning
and counted, and nothing is planned from it. Both halves are taken serialized and refused
unread if longer than a half can be (`msg_schemas.capped`): keypoints with a million points
would hold the executor for seconds while rclpy read them.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from geometry_msgs.msg import Point32, PointStamped, Polygon, PolygonStamped
from rclpy.node import Node

from constrained_diffusion_ros.planning.robot import RobotModel
from msg_schemas import TOPICS, qos_profile
from msg_schemas.capped import largest, read_capped
from msg_schemas.conversions import point_of, polygon_of, stamp_seconds
from sim_bridge.scene import KEYPOINTS_LOCAL
from sim_bridge.scene import observation as pusht_observation

KEYPOINTS = len(KEYPOINTS_LOCAL)  # the T block's keypoints in an observation
PENDING_HALVES = 64  # observation halves (keypoints or pusher) kept waiting for their other half


def keep_pending(pending: dict[float, np.ndarray], stamp: float, half: np.ndarray) -> None:
    """Keep one half of an observation until its other half comes, the oldest dropped past
    PENDING_HALVES: halves that never pair (a future stamp, a dead topic) cannot pile up."""
    pending.pop(stamp, None)
    pending[stamp] = half
    while len(pending) > PENDING_HALVES:
        del pending[next(iter(pending))]


def newest_only(endpoint):
    """A controller answers the state as it is now: each half's newest message only. A deeper
    queue, grown while the executor was held (a zone flood), had the node answer states a
    second old, and the robot execute their setpoints from where it was by then."""
    profile = qos_profile(endpoint)
    profile.depth = 1
    return profile


class ObservationInput:
    """Calls `on_pair(stamp, stamp_msg)` when both halves of a stamp are in; the node then
    `take`s the observation. `refused` counts the observations refused; `pusher` is the last
    plausible pusher position, `moved` how far it moved from the one before (None at a new
    episode: a stamp no later than the last). A new run whose first observations are refused
    stays new until one is taken: its later stamps may pass the old run's last.

    `taken` counts the observations taken; `late` those taken more than `late_s` (realtime: a
    control period; None in lockstep, where the robot waits for the answer) after their pusher
    half was published: the shield answers a state at most a period old (a setpoint that takes
    over a tick late, it allows for), so a late one is said on `/diagnostics`. The age is a
    difference of wall clocks (the publisher's source timestamp and this node's), exact on one
    machine and as good as their sync across machines. `handled_stamp` is the stamp of the
    last observation taken or refused."""

    def __init__(self, node: Node, robot: RobotModel,
                 on_pair: Callable[[float, object], None], late_s: float | None = None) -> None:
        self.node, self.robot, self.on_pair = node, robot, on_pair
        self.keypoints: dict[float, np.ndarray] = {}
        self.pushers: dict[float, np.ndarray] = {}
        self.published: dict[float, float] = {}  # the pusher halves' source timestamps (s)
        self.refused = 0
        self.taken, self.late, self.late_s = 0, 0, late_s
        self.age_s = float("nan")  # the last taken observation's, when it was taken
        self.handled_stamp = float("nan")
        self.pusher: np.ndarray | None = None
        self.pusher_stamp: float | None = None
        self.run_pending = False  # a new run began with refused observations: none taken yet
        self.moved: float | None = None
        self.caps = {PolygonStamped: largest(PolygonStamped(polygon=Polygon(
            points=[Point32()] * KEYPOINTS))), PointStamped: largest(PointStamped())}
        self.subscriptions = [
            node.create_subscription(PolygonStamped, TOPICS["keypoints"].name,
                                     self._capped(PolygonStamped, self._on_keypoints),
                                     newest_only(TOPICS["keypoints"]), raw=True),
            node.create_subscription(PointStamped, TOPICS["pusher"].name,
                                     self._capped(PointStamped, self._on_pusher),
                                     newest_only(TOPICS["pusher"]), raw=True)]

    def _capped(self, msg_type: type, callback: Callable) -> Callable[[bytes, dict], None]:
        """`callback` for the messages of `msg_type` no longer than a real one can be."""
        def on_serialized(data: bytes, info: dict) -> None:
            message, problem = read_capped(data, msg_type, self.caps[msg_type])
            if message is None:
                self.refused += 1
                self.node.get_logger().warning(
                    f"observation refused unread, last safe setpoint held: "
                    f"{msg_type.__name__} {problem}", throttle_duration_sec=1.0)
                return
            callback(message, info)
        return on_serialized

    def _on_keypoints(self, msg: PolygonStamped, _info: dict) -> None:
        if len(msg.polygon.points) != KEYPOINTS:
            self.node.get_logger().warning(
                f"keypoints need {KEYPOINTS} points, got {len(msg.polygon.points)}")
            return
        self._half(self.keypoints, msg.header.stamp, polygon_of(msg.polygon))

    def _on_pusher(self, msg: PointStamped, info: dict) -> None:
        keep_pending(self.published, stamp_seconds(msg.header.stamp),
                     info.get("source_timestamp", 0) * 1e-9 or time.time())
        self._half(self.pushers, msg.header.stamp, point_of(msg))

    def _half(self, pending: dict[float, np.ndarray], stamp_msg, half: np.ndarray) -> None:
        stamp = stamp_seconds(stamp_msg)
        keep_pending(pending, stamp, half)
        if stamp in self.keypoints and stamp in self.pushers:
            self.on_pair(stamp, stamp_msg)

    def status(self) -> dict[str, object]:
        return {"observations_refused": self.refused, "observations_taken": self.taken,
                "observations_late": self.late, "observation_age_ms": f"{1000 * self.age_s:.1f}",
                "observation_stamp": f"{self.handled_stamp:.9f}"}

    def starts_run(self, stamp: float) -> bool:
        """Whether an observation stamped `stamp` starts a new run (episode): it is the first,
        or no later than the last plausible one (the simulator was reset, stamps start again),
        or a new run none of whose observations was taken yet."""
        return self.pusher_stamp is None or self.run_pending or stamp <= self.pusher_stamp

    def ends_run(self, stamp: float) -> bool:
        """Whether `stamp` is the first sign that a run before has ended (counted once per
        reset, whether its first observation is taken or refused)."""
        return (self.pusher_stamp is not None and not self.run_pending
                and stamp <= self.pusher_stamp)

    def take(self, stamp: float) -> np.ndarray | None:
        """The observation of `stamp` from its two halves (older halves dropped), or None
        when it is refused (warned, counted)."""
        observation = pusht_observation(self.keypoints.pop(stamp), self.pushers.pop(stamp))
        self.age_s = time.time() - self.published.pop(stamp, time.time())
        self.handled_stamp = stamp
        for pending in (self.keypoints, self.pushers, self.published):
            for old in [s for s in pending if s < stamp]:
                del pending[old]
        pusher = self.robot.pusher(observation).astype(float)
        new_episode = self.starts_run(stamp)
        reason = "NaN/inf" if not np.all(np.isfinite(observation)) else \
            self.robot.implausible(pusher, None if new_episode else self.pusher,
                                   0.0 if new_episode else stamp - self.pusher_stamp)
        if reason is not None:
            self.refused += 1
            self.run_pending = new_episode
            self.node.get_logger().warning(
                f"observation refused, last safe setpoint held: {reason}",
                throttle_duration_sec=1.0)
            return None
        self.moved = None if new_episode else float(np.linalg.norm(pusher - self.pusher))
        self.pusher, self.pusher_stamp, self.run_pending = pusher, stamp, False
        self.taken += 1
        self.late += self.late_s is not None and self.age_s > self.late_s
        return observation
