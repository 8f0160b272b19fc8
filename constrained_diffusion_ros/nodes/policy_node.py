"""policy_node: the constrained diffusion policy as a ROS 2 node.

Two modes, as the simulator's. `lockstep` (default): every observation (keypoints + pusher with
the same stamp) is answered with one setpoint from the chunk in force, planned in the callback,
so a trial is deterministic and equals the in-process evaluation bit for bit. `realtime`: a
control clock publishes one setpoint per tick (`rate_hz`) from the latest observation while a
background thread plans the next chunk (`RealtimeController`); a zone that arrives is checked
at once and a safe setpoint published before the next tick. The clock is a thread of its own
(`ControlClock`) that only sends the setpoint already computed, so no callback or computation
delays it.

Zones come in through a `ZoneIngest` (zone_ingest.py), which owns the zone topics, keep-out
masks, the clear service and expiry; its counters are in the node's diagnostics (`/diagnostics`).
"""

from __future__ import annotations

import gc
import math
import pickle
import sys
import threading
import time

import numpy as np
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PolygonStamped
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from std_msgs.msg import Header

from constrained_diffusion_ros.nodes.zone_ingest import ZoneIngest
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.clock import ControlClock
from constrained_diffusion_ros.planning.config import load_configurations, safe_yaml
from constrained_diffusion_ros.planning.liveness import StandstillMeter
from constrained_diffusion_ros.planning.lockstep import LockstepLoop
from constrained_diffusion_ros.planning.os_scheduling import (
    CLOCK_PRIORITY,
    EXECUTOR_PRIORITY,
    request_fifo,
)
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.realtime import RealtimeController
from constrained_diffusion_ros.planning.robot import RobotModel
from constrained_diffusion_ros.policy.device import DEVICES
from constrained_diffusion_ros.policy.runtime import RUNTIMES, use_runtime
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea
from constrained_diffusion_ros.zones.geometry import leaves_no_room
from constrained_diffusion_ros.zones.grid import DEFAULT_THRESHOLD, MaskCaps
from constrained_diffusion_ros.zones.live import DEFAULT_MAX_VERTICES, DEFAULT_MAX_ZONES, LiveZones
from constrained_diffusion_ros.zones.plugins import load_area
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import (
    path_message,
    point_message,
    point_of,
    polygon_of,
    stamp_seconds,
    step_of_stamp,
)
from msg_schemas.parameters import Param, declare
from msg_schemas.spin import log_matches, spin_node
from msg_schemas.text import one_line
from sim_bridge.scene import observation as pusht_observation

MODES = ("lockstep", "realtime")
ROBOT_FIELDS = ("pusher_radius", "kp", "kv", "control_hz", "physics_hz")  # and workspace
PENDING_HALVES = 64  # observation halves (keypoints or pusher) kept waiting for their other half
# Their rise since the last report sets the diagnostic level.
HEALTH_COUNTERS = ("violations", "unsound_setpoints", "zones_refused", "masks_refused",
                   "observations_refused", "held_steps", "planning_errors")
STATUS_PERIOD_S = 0.5  # realtime: status this often

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
    Param("runtime", "auto", "what runs the network: onnxruntime (CPU, the fastest at batch "
          "1), torch, or auto: onnxruntime in realtime, torch in lockstep (bit for bit the "
          "in-process evaluation); where ONNX Runtime cannot run it faithfully, torch, said in "
          "one log line", read_only=True, choices=("auto", *RUNTIMES)),
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
        wanted = values["runtime"]
        if wanted == "auto":
            wanted = "onnxruntime" if self.mode == "realtime" else "torch"
        self.runtime = use_runtime(self.policy, wanted)
        self.configurations = load_configurations(values["configurations_file"])
        self.zones = LiveZones(values["max_zones"], values["max_vertices"],
                               plug_in_area(values["restricted_area"],
                                            values["restricted_area_parameters"],
                                            self.robot.workspace),
                               workspace=self.robot.workspace)
        if self.mode == "realtime" and values["planning_process"]:
            _check_picklable(self.zones.fixed, values["restricted_area"])
        self.noise_seed = values["noise_seed"]
        self.generator = torch.Generator().manual_seed(self.noise_seed)
        self.controller: RealtimeController | None = None
        self._use_configuration(values["configuration"])
        self.add_on_set_parameters_callback(self._on_parameters)

        self.setpoint_pub = self._publisher("setpoint", PointStamped)
        self.plan_pub = self._publisher("plan", PathMsg)
        self.status_pub = self._publisher("diagnostics", DiagnosticArray)
        log_matches(self, [self.setpoint_pub])  # who gets the first setpoint
        self._health_counts: dict[str, int] = {}
        # Zones first: when a zone and an observation are ready together, the zone is taken first.
        self.zone_ingest = ZoneIngest(
            self, self.zones, self.robot.workspace,
            MaskCaps(pieces=values["max_mask_pieces"], vertices=values["max_mask_vertices"]),
            self._zones_changed, realtime=self.mode == "realtime",
            marker_period_s=1.0 / self.rate_hz)
        self._subscribe("keypoints", PolygonStamped, self._on_keypoints)
        self._subscribe("pusher", PointStamped, self._on_pusher)
        # The last setpoint message: what the clock sends on each tick (realtime), what a
        # repeated observation gets again (lockstep).
        self._in_force: PointStamped | None = None
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
            self.create_timer(STATUS_PERIOD_S, self._on_status_timer)
        self.executor_priority = values["executor_priority"]
        self.executor_realtime: bool | None = None  # asked for on the executor's own thread

        self.keypoints: dict[float, np.ndarray] = {}
        self.pushers: dict[float, np.ndarray] = {}
        self.last_stamp = -1.0
        self.latest_stamp = None  # realtime: the newest observation's stamp
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
        if self.mode == "realtime":
            # What start-up built (policy, torch, rclpy) lives as long as the node: out of the
            # collector's sight, so a full collection does not hold the GIL to scan it all.
            gc.collect()
            gc.freeze()
        self.get_logger().info(
            f"{self.mode} policy from {self.get_parameter('model').value}, configuration "
            f"{self.config.name!r}, network on {self.runtime}")

    def destroy_node(self) -> None:
        self.zone_ingest.shutdown()
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
        self.lockstep_loop = LockstepLoop(self.planner, self.zones, self.generator)
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
                self._send(self.controller.observe(
                    step_of_stamp(stamp_msg, self.robot.control_hz), observation),
                    publish=False)
                self.waiting_for_plan = self.controller.waiting
            return
        if stamp == self.last_stamp:
            # The simulator re-sends an observation until answered: the answer may have been
            # lost to a subscriber not yet matched, so send it again (no new plan, no noise).
            if self._in_force is not None:
                self.setpoint_pub.publish(self._in_force)
            return
        observation = self._take_observation(stamp)
        if stamp < self.last_stamp or stamp == 0.0:  # the simulator was reset: a new episode
            self.lockstep_loop.reset(self.noise_seed)
        self.last_stamp = stamp
        if observation is None:
            self._refused_observation_answer(stamp_msg)
            return
        step = step_of_stamp(stamp_msg, self.robot.control_hz)
        started = time.perf_counter()
        setpoint = self.lockstep_loop.act(observation[None].astype(np.float32), step)[0]
        planning_ms = 1000 * (time.perf_counter() - started)
        self._send(setpoint, stamp_msg)
        if self.lockstep_loop.last_plan is not None:
            self._after_plan(self.lockstep_loop.last_plan.chunks[0])
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
            self._send(self.last_safe_setpoint, stamp_msg)

    def _on_tick(self) -> None:
        """Realtime, on the clock's thread: exactly one setpoint per tick, the one computed
        last; nothing to wait on but the short lock around sending."""
        with self._send_lock:
            if self._in_force is None:
                return
            try:
                self.setpoint_pub.publish(self._in_force)
            except RCLError:  # shutting down: the context went away under the clock
                if self.context.ok():
                    raise

    def _send(self, setpoint: np.ndarray | None, stamp=None, publish: bool = True
              ) -> float | None:
        """Every setpoint goes out here: made sound (`_sendable`), stamped with its
        observation's stamp (exact nanoseconds: lockstep matches it; realtime: the newest
        observation's by default), kept as the one in force and published now if `publish`
        (realtime: else the clock sends it on its next tick). Returns when it was published
        (time.monotonic()), or None."""
        stamp = self.latest_stamp if stamp is None else stamp
        if setpoint is None or stamp is None:
            return None
        setpoint = self._sendable(setpoint)
        message = point_message(setpoint, stamp)
        sent = None
        with self._send_lock:  # a setpoint replaced is never sent after it
            self._in_force = message
            if publish:
                self.setpoint_pub.publish(message)
                sent = time.monotonic()
        self._count_violation(setpoint)
        return sent

    def _on_plan_ready(self) -> None:
        before = self.controller.stats.plans_installed
        self._send(self.controller.install_results(), publish=False)
        if self.controller.stats.plans_installed != before:
            self._after_plan(self.controller.chunk)

    def _on_status_timer(self) -> None:
        if self.executor_realtime is None:
            # On the thread that runs the callbacks: with FIFO priority it answers a zone
            # without waiting for other processes' time slices (the planning process, started
            # before, keeps normal scheduling).
            self.executor_realtime = request_fifo(self.executor_priority)
        self._publish_status(self.controller.stats.last_plan_ms)

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
                  "plans": self.lockstep_loop.stats.planner_calls,
                  "planning_ms": f"{planning_ms:.1f}",
                  "replan_latency_ms": f"{self.replan_latency_ms:.1f}",
                  "zone_to_setpoint_ms": f"{self.zone_to_setpoint_ms:.1f}",
                  "zones": len(self.zones), **self.zone_ingest.counts}
        if self.controller is not None:
            values.update(self.controller.status(), ticks=self.clock.ticks,
                          ticks_missed=self.clock.missed,
                          tick_late_p99_ms=f"{1000 * self.clock.late_p99():.1f}",
                          clock_realtime=self.clock.realtime,
                          executor_realtime=self.executor_realtime)
            values["planning_error"] = one_line(values["planning_error"] or "")
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

    def _zones_changed(self, received: float) -> None:
        """The zones in force changed (a message that came at `received`, time.monotonic()):
        in realtime the held setpoint is checked now and a safe one published at once (how long
        after: `zone_to_setpoint_ms` in the status)."""
        self.zone_change_time = time.monotonic()
        self.no_free_space = self._no_free_space()
        if self.controller is None:
            return

        def send(safe: np.ndarray) -> None:
            sent = self._send(safe)
            if sent is not None:
                self.zone_to_setpoint_ms = 1000 * (sent - received)

        self.controller.zones_changed(send)

    def _no_free_space(self) -> bool:
        """No setpoint is safe (the grown zones cover the workspace): the pusher is held where
        it is until space returns."""
        return leaves_no_room(self.zones.snapshot().geometry, self.robot.workspace,
                              self.robot.pusher_radius)


def main(args: list[str] | None = None) -> int:
    return spin_node(PolicyNode, "policy_node", args, PARAMETERS, __doc__)


if __name__ == "__main__":
    sys.exit(main())
