"""The simulator node itself (`sim_node` is its command): apart, so that `sim_node --help`
answers from the parameter table without importing rclpy."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

from geometry_msgs.msg import PointStamped, PolygonStamped, PoseStamped
from rclpy.clock import Clock as Clock_
from rclpy.clock import ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from msg_schemas import FRAME_ID, NAMESPACE, SERVICES, TOPICS, qos_profile
from msg_schemas.conversions import (
    point_message,
    polygon_message,
    pose2d_message,
    stamp_nanoseconds,
    stamp_of_step,
)
from msg_schemas.text import one_line
from node_support.parameters import Param, declare
from node_support.spin import log_matches
from sim_bridge.physics import PushTSim
from sim_bridge.scene import CONTROL_HZ, COORD_LIMITS

# Lockstep: while the sim waits for a setpoint it re-sends the current observation this often,
# so a subscriber that appears after the initial publish (discovery takes seconds) still gets
# it. The copies carry the same stamp; consumers drop observations whose stamp they have seen.
REPUBLISH_PERIOD_S = 0.5


def setpoint_fault(msg: PointStamped) -> str | None:
    """Why a setpoint cannot be executed, or None; checked where it arrives, before stepping."""
    if msg.header.frame_id not in ("", FRAME_ID):
        return f"frame_id {one_line(repr(msg.header.frame_id), 80)} is not {FRAME_ID!r}"
    x, y = msg.point.x, msg.point.y
    if not (math.isfinite(x) and math.isfinite(y)):
        return f"setpoint ({x}, {y}) is not finite"
    lo, hi = COORD_LIMITS
    if not (lo <= x <= hi and lo <= y <= hi):
        return f"setpoint ({x:g}, {y:g}) lies outside [{lo:g}, {hi:g}]"
    return None


def stale_setpoint(msg: PointStamped, newest_ns: int) -> bool:
    """Realtime: whether a setpoint is stamped later than the newest observation published in
    this run (`newest_ns`), so answers none of this run's: it is for the run before a reset,
    whose stamps went on to steps this run has not reached (or it is stamped on another clock).

    The rule's limits: stamps are the only evidence, so the old run's setpoints are told apart
    only while the new run's stamps are below theirs. One stamped at or before the newest
    observation passes: the old run's stamp 0 after a reset at step 0, or an old setpoint that
    arrives once the new run has passed its stamp (a reset after a few steps, a long delay).
    Unstamped setpoints (stamp 0) always pass.
    """
    return stamp_nanoseconds(msg.header.stamp) > newest_ns


class SimNode(Node):
    """Publishes the PushT scene and steps it on setpoints (lockstep) or on a timer (realtime)."""

    def __init__(self, parameters: Sequence[Param]) -> None:
        super().__init__("sim_node", namespace=NAMESPACE)
        values = declare(self, parameters)
        self.mode, rate_hz, self.max_steps = values["mode"], values["rate_hz"], values["max_steps"]

        self.sim = PushTSim()
        self.step_count = 0
        self.target: tuple[float, float] | None = None  # realtime: the setpoint held
        self.running = False  # false until the first reset when autostart is false
        self.stale_setpoints = 0  # realtime: dropped, stamped for another run
        self._limit_logged = False
        self._last_publish = 0.0

        def publisher(msg_type, topic: str):
            return self.create_publisher(msg_type, TOPICS[topic].name,
                                         qos_profile(TOPICS[topic], "publisher"))

        self.pose_pub = publisher(PoseStamped, "block_pose")
        self.score_pub = publisher(Float64, "score")
        self.keypoints_pub = publisher(PolygonStamped, "keypoints")
        self.pusher_pub = publisher(PointStamped, "pusher")
        self.clock_pub = publisher(Clock, "clock")
        log_matches(self, [self.pusher_pub, self.pose_pub])  # who gets the first observation
        setpoint = TOPICS["setpoint"]
        self.create_subscription(PointStamped, setpoint.name, self.on_setpoint,
                                 qos_profile(setpoint))
        self.create_service(Trigger, SERVICES["reset"].name, self.on_reset)
        # The sim is the source of /clock: it steps on the steady clock even with use_sim_time.
        steady = Clock_(clock_type=ClockType.STEADY_TIME)
        if self.mode == "realtime":
            self.create_timer(1.0 / rate_hz, self.on_tick, clock=steady)
        else:
            self.create_timer(REPUBLISH_PERIOD_S / 5, self.on_idle, clock=steady)

        seed = self.get_parameter("seed").value
        if values["autostart"]:
            self.reset(seed)  # a bad seed raises: main reports it
            self.get_logger().info(f"{self.mode} PushT sim running, seed {seed}")
        else:
            self.sim.reset(seed)  # checks the seed; publishes nothing yet
            self.get_logger().info(f"{self.mode} PushT sim waiting for a reset")

    # ---- simulation

    def reset(self, seed: int) -> None:
        self.sim.reset(seed)
        self.running = True
        self.step_count = 0
        self.target = None
        self._limit_logged = False
        self.publish_observation()

    def step(self, x: float, y: float) -> None:
        if self.max_steps > 0 and self.step_count >= self.max_steps:
            if not self._limit_logged:
                self.get_logger().info(f"max_steps {self.max_steps} reached: no more stepping")
                self._limit_logged = True
            return
        self.sim.step((x, y))
        self.step_count += 1
        self.publish_observation()

    def publish_observation(self) -> None:
        """Block pose, score, keypoints, then the pusher, all with one simulated-time stamp."""
        stamp = stamp_of_step(self.step_count, CONTROL_HZ)
        self.clock_pub.publish(Clock(clock=stamp))
        self.pose_pub.publish(pose2d_message(self.sim.block_pose, stamp))
        self.score_pub.publish(Float64(data=self.sim.score()))
        self.keypoints_pub.publish(polygon_message(self.sim.keypoints(), stamp))
        self.pusher_pub.publish(point_message(self.sim.state[:2], stamp))
        self._last_publish = time.monotonic()

    # ---- callbacks

    def on_setpoint(self, msg: PointStamped) -> None:
        if not self.running:
            self.get_logger().warning("ignoring setpoints until the first reset (autostart off)",
                                      throttle_duration_sec=5.0)
            return
        fault = setpoint_fault(msg)
        if fault is not None:
            self.get_logger().warning(f"ignoring setpoint: {fault}")
            return
        if self.mode == "realtime":
            newest = stamp_nanoseconds(stamp_of_step(self.step_count, CONTROL_HZ))
            if stale_setpoint(msg, newest):
                self.stale_setpoints += 1
                self.get_logger().warning(
                    f"dropped {self.stale_setpoints} setpoint(s) stamped later than the newest "
                    f"observation ({newest * 1e-9:.1f} s): another run's, or not simulated "
                    f"time; this one {stamp_nanoseconds(msg.header.stamp) * 1e-9:.1f} s",
                    throttle_duration_sec=1.0)
                return
            self.target = (msg.point.x, msg.point.y)
            return
        current = stamp_of_step(self.step_count, CONTROL_HZ)
        if stamp_nanoseconds(msg.header.stamp) != stamp_nanoseconds(current):
            return  # answers another observation (a duplicate of one already stepped past)
        try:
            self.step(msg.point.x, msg.point.y)
        except ValueError as error:  # the simulator's own check, should the two ever differ
            self.get_logger().warning(f"ignoring setpoint: {error}")

    def on_tick(self) -> None:
        """Realtime: one control step toward the held setpoint (the pusher itself before any)."""
        if not self.running:
            return
        if self.target is None:
            self.target = tuple(float(v) for v in self.sim.state[:2])
        self.step(*self.target)

    def on_idle(self) -> None:
        """Lockstep: re-send the observation while no setpoint has answered it (see above)."""
        finished = self.max_steps > 0 and self.step_count >= self.max_steps
        if self.running and not finished and \
                time.monotonic() - self._last_publish >= REPUBLISH_PERIOD_S:
            self.publish_observation()

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        seed = self.get_parameter("seed").value
        try:
            self.reset(seed)
        except ValueError as error:
            response.success, response.message = False, f"reset refused: {error}"
            self.get_logger().error(response.message)
            return response
        response.success, response.message = True, f"reset to seed {seed}"
        self.get_logger().info(response.message)
        return response
