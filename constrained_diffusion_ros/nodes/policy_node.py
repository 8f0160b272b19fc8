"""policy_node: the constrained diffusion policy as a ROS 2 node.

Two modes, as the simulator's. `lockstep` (default): every observation (keypoints + pusher with
the same stamp) is answered with one setpoint from the chunk in force, planned in the callback,
so a trial is deterministic and equals the in-process evaluation bit for bit. `realtime`: a
control clock publishes one setpoint per tick (`rate_hz`) from the latest observation while a
background thread plans the next chunk (`RealtimeController`); a zone that arrives is checked
at once and a safe setpoint published before the next tick. The clock is a thread of its own
(`ControlClock`) that only sends the setpoint already computed, so no callback or computation
delays it.

Zones come in as id-keyed polygons, taken in batches as fast as they come and coalesced to the
last message per id; a malformed one, or one over the caps, is refused with a warning while the
zones in force stay in force. Counters of both are in the node's diagnostics (`/diagnostics`).
"""

from __future__ import annotations

import gc
import json
import math
import os
import pickle
import sys
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PolygonInstanceStamped, PolygonStamped
from nav_msgs.msg import OccupancyGrid
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.clock import ControlClock
from constrained_diffusion_ros.planning.config import load_configurations, safe_yaml
from constrained_diffusion_ros.planning.executor import ChunkExecutor
from constrained_diffusion_ros.planning.liveness import StandstillMeter
from constrained_diffusion_ros.planning.os_scheduling import (
    CLOCK_PRIORITY,
    EXECUTOR_PRIORITY,
    request_fifo,
)
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.realtime import RealtimeController
from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.policy.device import DEVICES
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.grid import (
    DEFAULT_THRESHOLD,
    BuiltMask,
    MaskBuilder,
    MaskCaps,
    build_mask,
)
from constrained_diffusion_ros.zones.live import (
    DEFAULT_MAX_VERTICES,
    DEFAULT_MAX_ZONES,
    BatchOutcome,
    LiveZones,
)
from constrained_diffusion_ros.zones.plugins import load_area
from msg_schemas import FRAME_ID, NAMESPACE, SERVICES, TOPICS, qos_profile
from msg_schemas.conversions import (
    path_message,
    point_message,
    point_of,
    polygon_of,
    stamp_seconds,
    step_of_stamp,
    zone_markers,
)
from msg_schemas.parameters import Param, declare
from msg_schemas.spin import log_matches, spin_node
from msg_schemas.text import one_line
from sim_bridge.scene import observation as pusht_observation

MODES = ("lockstep", "realtime")
ROBOT_FIELDS = ("pusher_radius", "kp", "kv", "control_hz", "physics_hz")  # and workspace
ZONE_BATCH_MAX = 10_000  # zone messages taken in one callback at most
PENDING_HALVES = 64  # observation halves (keypoints or pusher) kept waiting for their other half
MARKER_NAMESPACE = "zones"  # zone markers: marker namespace <node namespace>/zones, id = zone id
# Their rise since the last report sets the diagnostic level.
HEALTH_COUNTERS = ("violations", "unsound_setpoints", "zones_refused", "masks_refused",
                   "observations_refused", "held_steps", "planning_errors")
STATUS_PERIOD_S = 0.5  # realtime: status this often (zone markers: at most once per tick)

PARAMETERS = (
    Param("model", str(default_model_dir()), "policy directory (config.json + "
          "model.safetensors)", read_only=True),
    Param("configuration", "r_g10_p_safe", "constraint configuration, a name from the "
          "configurations file; settable at run time"),
    Param("configurations_file", str(config_dir() / "configurations.yaml"),
          "constraint configurations YAML", read_only=True),
    Param("noise_seed", 0, "seed of the denoising noise (deterministic trials)", read_only=True,
          low=0),
    Param("zone_lifetime", 0.0, "s; a zone not re-published within it expires; 0: never",
          low=0.0),
    Param("mode", "lockstep", "lockstep: one setpoint per observation, planned in the "
          "callback; realtime: one per tick of rate_hz, planned in the background",
          read_only=True, choices=MODES),
    Param("rate_hz", 10.0, "realtime: setpoints per second", read_only=True, low=0.1,
          high=1000.0),
    Param("lead", -1, "realtime: steps before the chunk runs out at which the next plan "
          "starts; -1: from the measured planning time", read_only=True, low=-1),
    Param("prefix_soft", 4, "realtime: waypoints after the committed ones drawn toward the "
          "chunk in force; -1: no inpainting", read_only=True, low=-1),
    Param("executor_priority", EXECUTOR_PRIORITY, "realtime: SCHED_FIFO priority of the "
          f"executor thread, which answers zones and observations (the clock has "
          f"{CLOCK_PRIORITY}); 0: normal scheduling", read_only=True, low=0, high=98),
    Param("torch_threads", 1, "torch threads of the planner (1 is best on 2 cores; about "
          "half the cores on bigger machines)", read_only=True, low=1, high=256),
    Param("device", "cpu", f"where the network runs: {DEVICES} (the zones stay on the CPU)",
          read_only=True),
    Param("planning_process", True, "realtime: plan in a child process, so planning never "
          "holds the interpreter lock that the clock and zone callbacks need; false: in a "
          "thread (a restricted_area plug-in that cannot be pickled needs it)", read_only=True),
    Param("planning_idle", True, "realtime: the planning process at idle priority (SCHED_IDLE: "
          "whatever else wakes runs first) where the node may raise it again (CAP_SYS_NICE "
          "or RLIMIT_NICE), and at nice 5 for good once it gets under a quarter of a core; false: "
          "nice 5 throughout", read_only=True),
    Param("max_zones", DEFAULT_MAX_ZONES, "zones in force at most; more are refused",
          read_only=True, low=1),
    Param("max_vertices", DEFAULT_MAX_VERTICES, "vertices per zone at most", read_only=True,
          low=3),
    Param("max_mask_pieces", MaskCaps.pieces, "keep-out mask: pieces (separate regions) at "
          "most; a finer mask is refused", read_only=True, low=1),
    Param("max_mask_vertices", MaskCaps.vertices, "keep-out mask: vertices of all its pieces "
          "at most; a finer mask is refused", read_only=True, low=4),
    Param("keepout_threshold", DEFAULT_THRESHOLD, "keep-out mask cells at or above it are "
          "restricted (nav2's occupied threshold, 0..100)", low=1, high=100),
    Param("restricted_area", "", "a plug-in check always in force: 'package.module:Class' or "
          "an entry point of group constrained_diffusion_ros.restricted_areas; empty: none",
          read_only=True),
    Param("restricted_area_parameters", "", "its keyword arguments, a YAML mapping, e.g. "
          "'{config_file: camera_zones.yaml}'", read_only=True),
    # What the planner knows of the robot (PushT's by default), read at start.
    Param("robot.pusher_radius", float(PUSHT_ROBOT.pusher_radius),
          "px; zones grown by it keep the pusher's body out", read_only=True, low=0.0),
    Param("robot.workspace", [float(v) for v in PUSHT_ROBOT.workspace],
          "px: x_min, y_min, x_max, y_max; outside counts as restricted", read_only=True),
    Param("robot.kp", float(PUSHT_ROBOT.kp), "PD gain on position (1/s^2)", read_only=True,
          low=0.0),
    Param("robot.kv", float(PUSHT_ROBOT.kv), "PD gain on velocity (1/s)", read_only=True,
          low=0.0),
    Param("robot.control_hz", float(PUSHT_ROBOT.control_hz), "setpoints per second; stamps "
          "are control steps at this rate", read_only=True, low=0.1),
    Param("robot.physics_hz", float(PUSHT_ROBOT.physics_hz), "PD integration rate the shield "
          "predicts the pusher with", read_only=True, low=0.1),
)


def keep_pending(pending: dict[float, np.ndarray], stamp: float, half: np.ndarray) -> None:
    """Keep one half of an observation until its other half comes, the oldest dropped past
    PENDING_HALVES: halves that never pair (a future stamp, a dead topic) cannot pile up."""
    pending.pop(stamp, None)
    pending[stamp] = half
    while len(pending) > PENDING_HALVES:
        del pending[next(iter(pending))]


def plug_in_area(spec: str, parameters: str, workspace: Bounds) -> RestrictedArea | None:
    """The plug-in check named by the parameters, probed over `workspace`, or None;
    ValueError with one line."""
    if not spec:
        return None
    keywords = safe_yaml(parameters, "parameter restricted_area_parameters") \
        if parameters else {}
    if not isinstance(keywords, dict):
        raise ValueError(f"parameter restricted_area_parameters must be a mapping, got "
                         f"{parameters!r}")
    return load_area(spec, keywords, workspace=workspace)


def _check_picklable(area: RestrictedArea | None, spec: str) -> None:
    """The planning process gets the zones by pickle: a plug-in area that cannot be pickled is
    refused at start, in one line, rather than failing every plan."""
    if area is None:
        return
    try:
        pickle.dumps(area)
    except Exception as error:
        raise ValueError(f"restricted_area {spec!r} cannot be sent to the planning process "
                         f"({one_line(error)}); set planning_process:=false") from None


class PolicyNode(Node):
    def __init__(self) -> None:
        super().__init__("policy_node", namespace=NAMESPACE)
        values = declare(self, PARAMETERS)
        self.mode, self.rate_hz = values["mode"], values["rate_hz"]
        self.lead, self.soft, threads = values["lead"], values["prefix_soft"], \
            values["torch_threads"]
        torch.set_num_threads(threads)
        if self.mode == "realtime":  # the clock thread waits at most 0.2 ms for another's GIL
            sys.setswitchinterval(0.0002)
        self.robot = RobotModel(
            **{name: values[f"robot.{name}"] for name in ROBOT_FIELDS},
            workspace=tuple(values["robot.workspace"]),
            pusher_in_observation=PUSHT_ROBOT.pusher_in_observation)
        self.policy = load_policy(values["model"], values["device"])
        self.configurations = load_configurations(values["configurations_file"])
        self.zones = LiveZones(values["max_zones"], values["max_vertices"],
                               plug_in_area(values["restricted_area"],
                                            values["restricted_area_parameters"],
                                            self.robot.workspace),
                               workspace=self.robot.workspace)
        if self.mode == "realtime" and values["planning_process"]:
            _check_picklable(self.zones.fixed, values["restricted_area"])
        # $ROS_HOME/constrained_diffusion_ros/<node>.cleared: the (id, stamp) of cleared zones,
        # so their replays stay gone after a restart (exact messages: any clock, any publisher).
        ros_home = Path(os.environ.get("ROS_HOME") or Path.home() / ".ros")
        self.clear_file = ros_home / "constrained_diffusion_ros" / (
            self.get_fully_qualified_name().strip("/").replace("/", "__") + ".cleared")
        self.zones.cleared = self._remembered_clears()
        self.zone_counts = {"zone_messages": 0, "zones_applied": 0, "zones_refused": 0,
                            "zones_stale": 0, "zone_batches": 0, "masks_applied": 0,
                            "masks_refused": 0}
        self.noise_seed = values["noise_seed"]
        self.generator = torch.Generator().manual_seed(self.noise_seed)
        self.controller: RealtimeController | None = None
        self._use_configuration(values["configuration"])
        self.add_on_set_parameters_callback(self._on_parameters)

        self.setpoint_pub = self._publisher("setpoint", PointStamped)
        self.plan_pub = self._publisher("plan", PathMsg)
        self.marker_pub = self._publisher("zone_markers", MarkerArray)
        self.status_pub = self._publisher("diagnostics", DiagnosticArray)
        log_matches(self, [self.setpoint_pub])  # who gets the first setpoint
        self._health_counts: dict[str, int] = {}
        # Zones first: when a zone and an observation are ready together, the zone is taken first.
        # From any publisher: a volatile subscription matches every one, a transient-local one
        # also gets a latched publisher's history when this node (re)starts; a message both
        # deliver is taken once.
        latched = qos_profile(TOPICS["zones"])
        volatile = qos_profile(TOPICS["zones"])
        volatile.durability = DurabilityPolicy.VOLATILE
        self.zone_subs = [self.create_subscription(PolygonInstanceStamped, TOPICS["zones"].name,
                                                   self._on_zone, profile)
                          for profile in (volatile, latched)]
        self._zone_messages_seen: OrderedDict[tuple, None] = OrderedDict()
        self._zones_paced_until = 0.0  # realtime: no zone batch before then (`_on_zone`)
        self._subscribe("keepout_mask", OccupancyGrid, self._on_keepout_mask)
        self.keepout_ids: list[str] = []
        self.mask_caps = MaskCaps(pieces=values["max_mask_pieces"],
                                  vertices=values["max_mask_vertices"])
        self.mask_builder: MaskBuilder | None = None
        if self.mode == "realtime":  # masks built off the thread that answers zones
            self._mask_ready = self.create_guard_condition(self._on_mask_ready)
            self._built_mask: BuiltMask | None = None
            self.mask_builder = MaskBuilder(self._on_mask_built, self.mask_caps,
                                            self.robot.workspace)
        self._subscribe("keypoints", PolygonStamped, self._on_keypoints)
        self._subscribe("pusher", PointStamped, self._on_pusher)
        self.create_service(Trigger, SERVICES["clear_zones"].name, self._on_clear)
        self.create_timer(0.2, self._expire_zones)
        self._markers_due = False
        self._held: PointStamped | None = None  # realtime: what the clock sends
        self._send_lock = threading.Lock()  # a setpoint replaced is never sent after it
        if self.mode == "realtime":
            wake = self.create_guard_condition(self._on_plan_ready)
            self.controller = RealtimeController(
                self.planner, self.zones, self.rate_hz, None if self.lead < 0 else self.lead,
                self.soft, self.noise_seed, wake.trigger,
                threads if values["planning_process"] else None, values["planning_idle"])
            self.clock = ControlClock(self.rate_hz, self._on_tick)
            if not self.clock.realtime:
                self.get_logger().warning(
                    "control clock without real-time priority (not allowed here: raise "
                    "rtprio in /etc/security/limits.conf); ticks may be late on a busy machine")
            self.create_timer(1.0 / self.rate_hz, self._on_markers_timer)
            self.create_timer(STATUS_PERIOD_S, self._on_status_timer)
        self.executor_priority = values["executor_priority"]
        self.executor_realtime: bool | None = None  # asked for on the executor's own thread

        self.keypoints: dict[float, np.ndarray] = {}
        self.pushers: dict[float, np.ndarray] = {}
        self.last_stamp = -1.0
        self.latest_stamp = None  # realtime: the newest observation's stamp
        self.last_setpoint: PointStamped | None = None
        self.violations = 0
        self.unsound_setpoints = 0  # non-finite or outside the workspace: the pusher held
        self.no_free_space = False  # the zones cover the whole workspace
        self.latest_pusher: np.ndarray | None = None  # the last plausible one
        self.pusher_stamp: float | None = None  # its observation's stamp
        self.last_safe_setpoint: np.ndarray | None = None
        self.observations_refused = 0
        # The pusher parked at a zone's edge: with a waypoint to execute (the filter's doing),
        # and while the last setpoint is held waiting for a plan (planning's).
        self.standstills, self.standstills_waiting = StandstillMeter(), StandstillMeter()
        self.waiting_for_plan = False  # the last step had no waypoint
        self.zone_change_time: float | None = None
        self.replan_latency_ms = float("nan")
        self.zone_to_setpoint_ms = float("nan")  # the last safe setpoint sent for a zone
        if self.zones.fixed is not None:
            self._publish_markers()  # viewers see the plug-in check from the start
        if self.mode == "realtime":
            # What start-up built (policy, torch, rclpy) lives as long as the node: out of the
            # collector's sight, so a full collection does not hold the GIL to scan it all.
            gc.collect()
            gc.freeze()
        self.get_logger().info(
            f"{self.mode} policy from {self.get_parameter('model').value}, configuration "
            f"{self.config.name!r}")

    def destroy_node(self) -> None:
        if self.mask_builder is not None:
            self.mask_builder.shutdown()
        if self.controller is not None:
            self.clock.shutdown()
            self.controller.shutdown()
        super().destroy_node()

    # -- wiring ---------------------------------------------------------------------------------

    def _publisher(self, topic: str, msg_type):
        return self.create_publisher(msg_type, TOPICS[topic].name,
                                     qos_profile(TOPICS[topic], "publisher"))

    def _subscribe(self, topic: str, msg_type, callback):
        return self.create_subscription(msg_type, TOPICS[topic].name, callback,
                                        qos_profile(TOPICS[topic]))

    def _use_configuration(self, name: str) -> None:
        if name not in self.configurations:
            raise ValueError(f"unknown configuration {name!r}; known: "
                             f"{', '.join(self.configurations)}")
        self.config = self.configurations[name]
        self.planner = ConstrainedPlanner(self.policy, self.config, self.robot)
        self.chunk_executor = ChunkExecutor(self.planner, self.zones, self.generator)
        if self.controller is not None:
            self.controller.use_planner(self.planner)

    def _on_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == "configuration":
                try:
                    self._use_configuration(parameter.value)
                except ValueError as error:
                    return SetParametersResult(successful=False, reason=str(error))
                self.get_logger().info(f"configuration now {parameter.value!r}")
        return SetParametersResult(successful=True)

    # -- observations -> setpoints ----------------------------------------------------------------

    def _on_keypoints(self, msg: PolygonStamped) -> None:
        if len(msg.polygon.points) != 9:
            self.get_logger().warning(f"keypoints need 9 points, got {len(msg.polygon.points)}")
            return
        stamp = stamp_seconds(msg.header.stamp)
        keep_pending(self.keypoints, stamp, polygon_of(msg.polygon))
        self._maybe_act(stamp, msg.header.stamp)

    def _on_pusher(self, msg: PointStamped) -> None:
        stamp = stamp_seconds(msg.header.stamp)
        keep_pending(self.pushers, stamp, point_of(msg))
        self._maybe_act(stamp, msg.header.stamp)

    def _maybe_act(self, stamp: float, stamp_msg) -> None:
        if stamp not in self.keypoints or stamp not in self.pushers:
            return
        if self.controller is not None:  # realtime: the setpoint the clock sends from now on
            observation = self._take_observation(stamp)
            if observation is not None:
                self.latest_stamp = stamp_msg
                held_before = self.controller.stats.held_steps
                self._hold(self.controller.observe(
                    step_of_stamp(stamp_msg, self.robot.control_hz), observation))
                self.waiting_for_plan = self.controller.stats.held_steps > held_before
            return
        if stamp == self.last_stamp:
            # The simulator re-sends an observation until answered: the answer may have been
            # lost to a subscriber not yet matched, so send it again (no new plan, no noise).
            if self.last_setpoint is not None:
                self.setpoint_pub.publish(self.last_setpoint)
            return
        observation = self._take_observation(stamp)
        if stamp < self.last_stamp or stamp == 0.0:  # the simulator was reset: a new episode
            self.chunk_executor.reset(self.noise_seed)
        self.last_stamp = stamp
        if observation is None:
            self._refused_observation_answer(stamp_msg)
            return
        step = step_of_stamp(stamp_msg, self.robot.control_hz)
        started = time.perf_counter()
        setpoint = self.chunk_executor.act(observation[None].astype(np.float32), step)[0]
        planning_ms = 1000 * (time.perf_counter() - started)
        self._publish_setpoint(setpoint, stamp_msg)
        if self.chunk_executor.last_plan is not None:
            self._after_plan(self.chunk_executor.last_plan.chunks[0])
        self._publish_status(planning_ms)

    def _take_observation(self, stamp: float) -> np.ndarray | None:
        """The observation of `stamp` from its two messages, older halves dropped; None (with
        a warning, counted) when it is not finite or its pusher cannot be the robot's (out of
        the workspace, or a jump no PD pusher can make): nothing is planned from it, and the
        last safe setpoint stays."""
        observation = pusht_observation(self.keypoints.pop(stamp), self.pushers.pop(stamp))
        for pending in (self.keypoints, self.pushers):
            for old in [s for s in pending if s < stamp]:
                del pending[old]
        pusher = self.robot.pusher(observation).astype(float)
        new_episode = self.pusher_stamp is None or stamp <= self.pusher_stamp
        reason = "NaN/inf" if not np.all(np.isfinite(observation)) else \
            self.robot.implausible(pusher, None if new_episode else self.latest_pusher,
                                   0.0 if new_episode else stamp - self.pusher_stamp)
        if reason is not None:
            self.observations_refused += 1
            self.get_logger().warning(f"observation refused, last safe setpoint held: {reason}",
                                      throttle_duration_sec=1.0)
            return None
        if new_episode:
            self.standstills.reset_run()
            self.standstills_waiting.reset_run()
        else:
            self._measure_standstill(pusher)
        self.latest_pusher, self.pusher_stamp = pusher, stamp
        return observation

    def _measure_standstill(self, pusher: np.ndarray) -> None:
        """One more step for the standstill count: how far the pusher moved, how near a zone."""
        area = self.zones.area_at(0)
        clearance = math.inf if area is None else \
            float(area.signed_distance(torch.from_numpy(pusher[None]))[0])
        moved = float(np.linalg.norm(pusher - self.latest_pusher))
        counting, other = (self.standstills_waiting, self.standstills) if self.waiting_for_plan \
            else (self.standstills, self.standstills_waiting)
        counting.update(moved, clearance, self.robot.pusher_radius)
        other.reset_run()

    def _sendable(self, setpoint: np.ndarray) -> np.ndarray:
        """Never a non-finite or out-of-workspace setpoint, nor any while zones leave the
        pusher no free space; reported as ERROR until setpoints are sound again. In their
        place: while there is no free space, the pusher's own (plausible) position; else the
        last setpoint sent, if it is still outside every zone; else the pusher's position."""
        if not self.no_free_space and np.all(np.isfinite(setpoint)) \
                and not self.robot.outside(setpoint):
            self.last_safe_setpoint = setpoint
            return setpoint
        self.unsound_setpoints += 1
        self.get_logger().error(f"no sound setpoint ({setpoint.tolist()}): holding the pusher",
                                throttle_duration_sec=1.0)
        last = self.last_safe_setpoint
        if not self.no_free_space and last is not None and not self._inside_zone(last):
            return last
        x_min, y_min, x_max, y_max = self.robot.workspace
        return np.clip(self.latest_pusher, (x_min, y_min), (x_max, y_max))

    def _refused_observation_answer(self, stamp_msg) -> None:
        """Lockstep: the simulator waits for an answer to every observation; a refused one gets
        the last safe setpoint (none before the first)."""
        if self.last_safe_setpoint is not None:
            self._publish_setpoint(self.last_safe_setpoint, stamp_msg)

    def _on_tick(self) -> None:
        """Realtime, on the clock's thread: exactly one setpoint per tick, the one computed
        last; nothing to wait on but the short lock around sending."""
        with self._send_lock:
            if self._held is None:
                return
            try:
                self.setpoint_pub.publish(self._held)
            except RCLError:  # shutting down: the context went away under the clock
                if self.context.ok():
                    raise

    def _hold(self, setpoint: np.ndarray | None, send_now: bool = False) -> float | None:
        """Realtime: `setpoint` is what the clock sends from now on (sent at once if asked);
        when it was sent (time.monotonic()), or None if it was not."""
        if setpoint is None or self.latest_stamp is None:
            return None
        setpoint = self._sendable(setpoint)
        message = point_message(setpoint, self.latest_stamp)
        sent = None
        with self._send_lock:
            self._held = message
            if send_now:
                self.setpoint_pub.publish(message)
                sent = time.monotonic()
        self._count_violation(setpoint)
        return sent

    def _on_markers_timer(self) -> None:
        if self._markers_due:  # viewers see zone changes at most once per tick
            self._markers_due = False
            self._publish_markers()

    def _on_plan_ready(self) -> None:
        before = self.controller.stats.plans_installed
        self._hold(self.controller.install_results())
        if self.controller.stats.plans_installed != before:
            chunk = self.controller.queue.waypoints[0]
            self._after_plan(chunk)

    def _on_status_timer(self) -> None:
        if self.executor_realtime is None:
            # On the thread that runs the callbacks: with FIFO priority it answers a zone
            # without waiting for other processes' time slices (the planning process, started
            # before, keeps normal scheduling).
            self.executor_realtime = request_fifo(self.executor_priority)
        self._publish_status(self.controller.stats.last_plan_ms)

    def _publish_setpoint(self, setpoint: np.ndarray, stamp_msg) -> None:
        """Stamped with the observation's own stamp (exact nanoseconds): lockstep matches it."""
        setpoint = self._sendable(setpoint)
        msg = point_message(setpoint, stamp_msg)
        self.setpoint_pub.publish(msg)
        self.last_setpoint = msg
        self._count_violation(setpoint)

    def _count_violation(self, setpoint: np.ndarray) -> None:
        if self._inside_zone(setpoint):
            self.violations += 1

    def _inside_zone(self, setpoint: np.ndarray) -> bool:
        area = self.zones.area_at(0)
        return area is not None and bool(area.contains(torch.tensor(setpoint[None]))[0])

    def _after_plan(self, chunk: np.ndarray) -> None:
        if self.zone_change_time is not None:
            self.replan_latency_ms = 1000 * (time.monotonic() - self.zone_change_time)
            self.zone_change_time = None
        self.plan_pub.publish(path_message(chunk, self.get_clock().now().to_msg()))

    def _publish_status(self, planning_ms: float) -> None:
        values = {"configuration": self.config.name, "mode": self.mode,
                  "violations": self.violations, "unsound_setpoints": self.unsound_setpoints,
                  "observations_refused": self.observations_refused,
                  "standstill_steps": self.standstills.steps,
                  "standstill_longest_s": f"{self.standstills.longest / self.robot.control_hz:.1f}",
                  "standstill_waiting_steps": self.standstills_waiting.steps,
                  "plans": self.chunk_executor.stats.planner_calls,
                  "planning_ms": f"{planning_ms:.1f}",
                  "replan_latency_ms": f"{self.replan_latency_ms:.1f}",
                  "zone_to_setpoint_ms": f"{self.zone_to_setpoint_ms:.1f}",
                  "zones": len(self.zones), **self.zone_counts}
        if self.controller is not None:
            stats = self.controller.stats
            values.update(plans=stats.plans_installed, plans_dropped=stats.plans_dropped,
                          plans_cancelled=self.controller.worker.cancelled,
                          waypoints_skipped=self.controller.queue.skipped,
                          held_steps=stats.held_steps, zone_reactions=stats.zone_reactions,
                          lead=self.controller.lead, ticks=self.clock.ticks,
                          ticks_missed=self.clock.missed,
                          tick_late_p99_ms=f"{1000 * self.clock.late_p99():.1f}",
                          clock_realtime=self.clock.realtime,
                          executor_realtime=self.executor_realtime,
                          planning_priority=self.controller.worker.priority,
                          planning_errors=self.controller.worker.errors,
                          planning_failed=self.controller.worker.failed,
                          planning_restarts=self.controller.worker.restarts,
                          planning_error=one_line(self.controller.worker.error or ""))
        values["zone_ids"] = ",".join(str(i) for i in self.zones.ids)
        level, message = self._health(values)
        status = DiagnosticStatus(level=level, name=self.get_fully_qualified_name(),
                                  message=message, hardware_id="pusht")
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        self.status_pub.publish(DiagnosticArray(header=Header(stamp=self.get_clock().now()
                                                             .to_msg()), status=[status]))

    def _health(self, values: dict) -> tuple[bytes, str]:
        """The diagnostic level since the last report: ERROR if a setpoint sent was inside a
        zone, WARN if zones were refused or (realtime) steps passed with no plan in time."""
        counts = {key: int(values.get(key, 0)) for key in HEALTH_COUNTERS}
        since = {key: counts[key] - self._health_counts.get(key, 0) for key in counts}
        self._health_counts = counts
        if since["unsound_setpoints"]:
            return DiagnosticStatus.ERROR, (
                f"no sound setpoint {since['unsound_setpoints']} time(s) (zones leave no free "
                f"space, or a non-finite action): the pusher held")
        if since["violations"]:
            return DiagnosticStatus.ERROR, f"{since['violations']} setpoint(s) inside a zone"
        if since["planning_errors"] or values.get("planning_failed"):
            # ERROR until a plan arrives again: a planner that died stays news until it plans
            return DiagnosticStatus.ERROR, (
                f"planning failed ({values['planning_errors']} fault(s), "
                f"{values['planning_restarts']} restart(s), no plan since): "
                f"{values['planning_error']}")
        problems = []
        if since["zones_refused"]:
            problems.append(f"{since['zones_refused']} zone message(s) refused")
        if since["masks_refused"]:
            problems.append(f"{since['masks_refused']} keep-out mask(s) refused")
        if since["observations_refused"]:
            problems.append(f"{since['observations_refused']} observation(s) refused (not "
                            f"finite, or a pusher that cannot be the robot's)")
        if since["held_steps"]:
            problems.append(f"planning missed its deadline ({since['held_steps']} step(s) "
                            f"with no waypoint)")
        if problems:
            return DiagnosticStatus.WARN, "; ".join(problems)
        return DiagnosticStatus.OK, "running"

    # -- zones ------------------------------------------------------------------------------------

    def _on_zone(self, msg: PolygonInstanceStamped, info: dict) -> None:
        """Takes every zone message waiting, not just this one: a flood is applied as one
        batch (the last message per id) and the union is rebuilt once, when next read.

        Realtime: a batch right after another first waits as long as the last one took, so a
        flood gets half the executor thread at most. Kept busy at SCHED_FIFO by a flood, the
        thread can be throttled by the kernel (its real-time budget spent) while it holds the
        interpreter lock, and the clock's ticks then wait for it (see docs/hostile_inputs.md);
        the wait coalesces the messages meanwhile, so nothing is lost and a zone waits no
        longer than behind a batch."""
        received = time.monotonic()
        if self.controller is not None and received < self._zones_paced_until:
            time.sleep(self._zones_paced_until - received)  # frees the CPU and the lock
        messages = [(msg, info)]
        for subscription in self.zone_subs:
            messages += self._take_waiting(subscription, ZONE_BATCH_MAX - len(messages))
        updates, refused = [], 0
        for message, message_info in messages:
            if self._seen_before(message, message_info):
                continue
            zone_id = int(message.polygon.id)
            if message.header.frame_id not in ("", FRAME_ID):
                refused += 1
                self.get_logger().warning(
                    f"zone {zone_id} refused: frame "
                    f"{one_line(repr(message.header.frame_id), 80)} is not {FRAME_ID!r}")
                continue
            stamp = stamp_seconds(message.header.stamp) or None  # 0: unstamped, from arrival
            updates.append((zone_id, [(p.x, p.y) for p in message.polygon.polygon.points],
                            stamp))
        lifetime = self.get_parameter("zone_lifetime").value or None
        outcome = self.zones.apply(updates, self._now(), lifetime)
        self._count_zones(outcome, refused)
        if outcome.changed:
            self._zones_changed(received)
        finished = time.monotonic()
        self._zones_paced_until = finished + (finished - max(received, self._zones_paced_until))

    def _on_keepout_mask(self, msg: OccupancyGrid) -> None:
        """A keep-out mask: its restricted cells become zones ("keepout/<k>", exact polygons)
        in place of the previous mask's; they do not expire. Realtime: built by the mask
        builder's thread, so zones and observations are answered meanwhile; lockstep: here, so
        a trial stays deterministic. Either way under the caps, which bound the build."""
        if msg.header.frame_id not in ("", FRAME_ID):
            self._refuse_mask(f"frame {one_line(repr(msg.header.frame_id), 80)} is not "
                              f"{FRAME_ID!r}")
            return
        info = msg.info
        grid = {"values": np.asarray(msg.data, dtype=np.int8), "resolution": info.resolution,
                "origin": (info.origin.position.x, info.origin.position.y),
                "threshold": self.get_parameter("keepout_threshold").value,
                "width": info.width, "height": info.height}
        stamp = stamp_seconds(msg.header.stamp) or None
        if self.mask_builder is not None:
            self.mask_builder.submit(stamp, **grid)
        else:
            self._take_mask(build_mask(grid, self.mask_caps, self.robot.workspace,
                                       stamp=stamp))

    def _on_mask_built(self, built: BuiltMask) -> None:
        """On the builder's thread: hand the mask to the executor's thread."""
        self._built_mask = built
        self._mask_ready.trigger()

    def _on_mask_ready(self) -> None:
        built, self._built_mask = self._built_mask, None
        if built is not None and built.sequence == self.mask_builder.latest:
            self._take_mask(built)

    def _refuse_mask(self, reason: str) -> None:
        self.zone_counts["masks_refused"] += 1
        self.get_logger().warning(f"keep-out mask refused, zones in force kept: {reason}")

    def _take_mask(self, built: BuiltMask) -> None:
        if built.polygons is None:
            self._refuse_mask(built.reason)
            return
        ids = [f"keepout/{k}" for k in range(len(built.polygons))]
        removed = [(old, []) for old in self.keepout_ids if old not in ids]
        # A mask's pieces are not messages: the caps on zone messages do not refuse them (the
        # mask's own caps did). Its stamp goes with them, so a clear outlives a restart.
        outcome = self.zones.apply([*removed, *((i, p, built.stamp) for i, p in
                                                zip(ids, built.polygons))],
                                   self._now(), capped=False)
        in_force = set(self.zones.ids)
        self.keepout_ids = [i for i in ids if i in in_force]
        self._count_zones(outcome, 0)
        self.zone_counts["masks_applied"] += 1
        self.get_logger().info(f"keep-out mask: {len(self.keepout_ids)} zone(s), built in "
                               f"{1000 * built.seconds:.0f} ms")
        if outcome.changed:
            self._zones_changed()

    def _seen_before(self, message: PolygonInstanceStamped, info: dict) -> bool:
        """Whether the other zone subscription already delivered this message (a latched
        publisher reaches both): same publication time, sequence number and id."""
        key = (info.get("source_timestamp"), info.get("publication_sequence_number"),
               message.polygon.id)
        if key in self._zone_messages_seen:
            return True
        self._zone_messages_seen[key] = None
        if len(self._zone_messages_seen) > 2 * ZONE_BATCH_MAX:
            self._zone_messages_seen.popitem(last=False)
        return False

    def _now(self) -> float:
        """s on the node's clock (sim time with use_sim_time), as zone stamps are."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _take_waiting(self, subscription, limit: int) -> list[tuple]:
        """The (message, info) pairs already queued on `subscription` (rclpy's own take, as
        its executor does), so a callback can handle a burst at once."""
        taken = []
        try:
            while len(taken) < limit:
                with subscription.handle:
                    got = subscription.handle.take_message(subscription.msg_type,
                                                           subscription.raw)
                if got is None:
                    break
                taken.append(got)
        except (AttributeError, TypeError):  # another rclpy: one message per callback
            pass
        return taken

    def _count_zones(self, outcome: BatchOutcome, refused_frames: int) -> None:
        counts = self.zone_counts
        counts["zone_batches"] += 1
        counts["zone_messages"] += outcome.received + refused_frames
        counts["zones_applied"] += outcome.applied
        counts["zones_refused"] += len(outcome.refused) + refused_frames
        counts["zones_stale"] += outcome.stale
        for zone_id, reason in outcome.refused:
            self.get_logger().warning(f"zone {zone_id} refused, zones in force kept: "
                                      f"{one_line(reason)}")

    def _zones_changed(self, received: float | None = None) -> None:
        """In realtime the held setpoint is checked now and a safe one published at once
        (how long after the zone callback began: `zone_to_setpoint_ms` in the status)."""
        self.zone_change_time = time.monotonic()
        received = self.zone_change_time if received is None else received
        self.no_free_space = self._no_free_space()
        if self.controller is None:
            self._publish_markers()
            return
        self._markers_due = True

        def send(safe: np.ndarray) -> None:
            sent = self._hold(safe, send_now=True)
            if sent is not None:
                self.zone_to_setpoint_ms = 1000 * (sent - received)

        self.controller.zones_changed(send)

    def _no_free_space(self) -> bool:
        """No setpoint is safe (the grown zones cover the workspace): the pusher is held where
        it is until space returns."""
        return leaves_no_room(self.zones.snapshot().geometry, self.robot.workspace,
                              self.robot.pusher_radius)

    def _expire_zones(self) -> None:
        if self.zones.expire(self._now()):
            self._zones_changed()

    def _on_clear(self, _request, response):
        count = len(self.zones)
        self.zones.clear()
        self._zones_changed()
        response.success, response.message = True, f"cleared {count} zones"
        try:  # remembered across restarts: latched publishers replay what was cleared
            self.clear_file.parent.mkdir(parents=True, exist_ok=True)
            self.clear_file.write_text(json.dumps(list(self.zones.cleared)))
        except OSError as error:
            self.get_logger().warning(f"cannot remember the clear in {self.clear_file} "
                                      f"({error.strerror}): a restart would revive the "
                                      f"cleared zones that latched publishers replay")
        return response

    def _remembered_clears(self) -> dict[tuple, None]:
        """The (id, stamp) of zones cleared by this node name in earlier runs."""
        try:
            pairs = json.loads(self.clear_file.read_text())
            return {(zone_id, float(stamp)): None for zone_id, stamp in pairs}
        except (OSError, ValueError, TypeError):
            return {}

    def _publish_markers(self) -> None:
        stamp = self.get_clock().now().to_msg()
        namespace = "/".join((self.get_namespace().rstrip("/"), MARKER_NAMESPACE))
        outlines = self.zones.outlines()
        for k, polygon in enumerate(getattr(self.zones.fixed, "polygons", None) or []):
            outlines[f"plugin/{k}"] = polygon  # a plug-in check that can show itself
        self.marker_pub.publish(zone_markers(outlines, stamp, namespace))


def main(args: list[str] | None = None) -> int:
    return spin_node(PolicyNode, "policy_node", args, PARAMETERS, __doc__)


if __name__ == "__main__":
    sys.exit(main())
