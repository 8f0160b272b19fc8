"""The policy node itself (`policy_node` is its command, and says what it does): apart, so
that `policy_node --help` answers from the parameter table without importing torch, rclpy
or the planning core."""

from __future__ import annotations

import gc
import logging
import sys
import time

import numpy as np
import torch
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import State, TransitionCallbackReturn

from constrained_diffusion_ros.nodes.observation_input import ObservationInput
from constrained_diffusion_ros.nodes.policy_parameters import (
    PARAMETERS,
    live_zones,
    robot_model,
    weaker_setting,
)
from constrained_diffusion_ros.nodes.policy_status import ReactionTimes, StatusReporter
from constrained_diffusion_ros.nodes.setpoint_output import SetpointOutput
from constrained_diffusion_ros.nodes.zone_ingest import ZoneIngest
from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.planning.config import load_configurations, weakens
from constrained_diffusion_ros.planning.liveness import StandstillCounts
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.sound_setpoints import SoundSetpoints
from constrained_diffusion_ros.policy.runtime import use_runtime
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.runtime.clock import ControlClock
from constrained_diffusion_ros.runtime.live_loop import live_chunk_loop, loop_status, warm_up
from constrained_diffusion_ros.runtime.os_scheduling import request_fifo
from constrained_diffusion_ros.zones.grid import MaskCaps
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import path_message, step_of_stamp
from msg_schemas.parameters import declare
from msg_schemas.spin import RosLogHandler, StartupPhases, log_matches
from msg_schemas.text import one_line

STATUS_PERIOD_S = 0.5  # realtime: status this often


# What a node is made of, and how each is destroyed: what configure built goes at cleanup.
ENTITIES = {"publishers": "destroy_publisher", "subscriptions": "destroy_subscription",
            "timers": "destroy_timer", "guards": "destroy_guard_condition",
            "services": "destroy_service", "clients": "destroy_client"}


class PolicyNode(LifecycleNode):
    """The policy as a managed (lifecycle) node, the convention nav2's nodes follow:
    configure loads the policy, starts the planning process and subscribes; activate sends
    setpoints; deactivate holds the last safe setpoint and sends none (zones are still taken);
    cleanup and shutdown free what configure built. With `autostart` it goes through configure
    and activate at start. `/diagnostics` gives its state (`lifecycle`) in every state."""

    def __init__(self) -> None:
        super().__init__("policy_node", namespace=NAMESPACE)
        # The package's Python log lines (the planning process's) go to /rosout too.
        package_log = logging.getLogger("constrained_diffusion_ros")
        package_log.addHandler(RosLogHandler(self.get_logger()))
        package_log.setLevel(logging.INFO)
        self.values = values = declare(self, PARAMETERS)
        self.mode, self.rate_hz = values["mode"], values["rate_hz"]
        self.realtime = self.mode == "realtime"
        self.status = StatusReporter(self)  # in every state
        self.lifecycle = "unconfigured"
        self.loop: ChunkLoop | None = None
        self.output: SetpointOutput | None = None
        self._built: set[tuple[str, object]] = set()  # what configure added to the node
        self._parameters_callback = None
        self._failure: BaseException | None = None  # why configure failed, for autostart
        if not values["autostart"]:
            self._say_state()
            return
        for transition in (self.trigger_configure, self.trigger_activate):
            if transition() != TransitionCallbackReturn.SUCCESS:
                raise self._failure or RuntimeError("the policy node could not activate")

    # -- lifecycle ----------------------------------------------------------------------------

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        before = self._entities()
        try:
            self._configure()
        except Exception as error:  # a bad parameter, file or plug-in: nothing is kept
            self._failure = error
            self._built = self._entities() - before
            self._free()
            if not self.values["autostart"]:  # (with it, the command says it and exits 2)
                self.get_logger().error(f"configure failed: {one_line(error)}")
            return TransitionCallbackReturn.FAILURE
        self._built = self._entities() - before
        return self._now("inactive")

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self.output.pause(False)
        return self._now("active")

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self.output.pause()  # the setpoint in force is held, and sent again on activate
        return self._now("inactive")

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._free()
        return self._now("unconfigured")

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._free()
        return self._now("finalized")

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self._free()
        return self._now("unconfigured")

    def _now(self, lifecycle: str) -> TransitionCallbackReturn:
        self.lifecycle = lifecycle
        self._say_state()
        return TransitionCallbackReturn.SUCCESS

    def _say_state(self) -> None:
        """The state on /diagnostics at once (with the counters once configured)."""
        if self.loop is not None:
            self._publish_status(self.loop.stats.last_plan_ms)
        else:
            self.status.publish({"lifecycle": self.lifecycle, "mode": self.mode})

    def _entities(self) -> set[tuple[str, object]]:
        return {(kind, entity) for kind in ENTITIES for entity in getattr(self, kind)}

    def _configure(self) -> None:
        startup = StartupPhases()
        # Settable parameters as they are now: they may have been set while unconfigured.
        self.values.update({param.name: self.get_parameter(param.name).value
                            for param in PARAMETERS if not param.read_only})
        values = self.values
        torch.set_num_threads(values["torch_threads"])
        if self.realtime:  # the clock thread waits at most 0.2 ms for another's GIL
            sys.setswitchinterval(0.0002)
        self.robot = robot_model(values)
        self.policy = load_policy(values["model"], values["device"])
        startup.mark("weights")
        runtime = values["runtime"]
        if runtime == "auto":
            runtime = "onnxruntime" if self.realtime else "torch"
        self.runtime = use_runtime(self.policy, runtime)
        startup.mark(self.runtime)
        self.configurations = load_configurations(values["configurations_file"])
        self.zones = live_zones(values, self.robot.workspace, self.robot.reaction_s)
        self.generator = torch.Generator().manual_seed(values["noise_seed"])
        self.configuration_changes = 0
        self.changes_refused = 0  # run-time parameter changes refused for weakening the filter
        self.runs_restarted = 0  # realtime: observations whose stamp went back (a new run)
        self.zone_updates_within_reach = 0  # moving zones' updates left to the next observation
        self._use_configuration(values["configuration"])
        startup.mark("planner and its worker")
        self._parameters_callback = self.add_on_set_parameters_callback(self._on_parameters)

        self.sound = SoundSetpoints(self.robot, self.zones)
        self.output = SetpointOutput(self, self.sound,
                                     values["executor_watchdog_s"] if self.realtime else 0.0)
        self.output.pause()  # until activated
        self.plan_pub = self.create_publisher(PathMsg, TOPICS["plan"].name,
                                              qos_profile(TOPICS["plan"], "publisher"))
        log_matches(self, [self.output.publisher])  # who gets the first setpoint
        # Zones first: when a zone and an observation are ready together, the zone is taken first.
        self.zone_ingest = ZoneIngest(
            self, self.zones, self.robot.workspace,
            MaskCaps(pieces=values["max_mask_pieces"], vertices=values["max_mask_vertices"]),
            self._zones_changed, realtime=self.realtime, marker_period_s=1.0 / self.rate_hz,
            alive=self.output.beat)
        self.observations = ObservationInput(self, self.robot, self._on_observation)
        self.last_stamp = -1.0  # lockstep: the observation answered last
        self.latest_stamp = None  # realtime: the newest observation's stamp
        self.standstills = StandstillCounts()  # the pusher parked at a zone's edge
        self.reaction = ReactionTimes()
        self.executor_realtime: bool | None = None  # asked for on the executor's own thread
        self.clock: ControlClock | None = None
        if self.realtime:
            # What start-up built (policy, torch, rclpy) lives as long as the node: out of the
            # collector's sight, so a full collection does not hold the GIL to scan it all.
            # Before the clock starts: this last full pass holds the GIL (about 150 ms on a
            # 2-core VM), and a clock thread cannot send a tick without it.
            gc.collect()
            gc.freeze()
            self.clock = ControlClock(self.rate_hz, self.output.repeat)
            if not self.clock.realtime:
                self.get_logger().warning(
                    "control clock without real-time priority (not allowed here: raise "
                    "rtprio in /etc/security/limits.conf); ticks may be late on a busy machine")
            self.create_timer(STATUS_PERIOD_S, self._on_status_timer)
            if values["executor_watchdog_s"] > 0:  # the clock's watchdog, fed 5x in its time,
                self.create_timer(values["executor_watchdog_s"] / 5, self.output.beat,
                                  clock=Clock(clock_type=ClockType.STEADY_TIME))  # sim time or not
        startup.mark("the rest")
        self.get_logger().info(
            f"{self.mode} policy from {values['model']}, configuration "
            f"{self.config.name!r}, network on {self.runtime}; start-up: {startup.text()}")

    def _free(self) -> None:
        """What configure built, stopped and destroyed (no setpoint after it starts)."""
        if self.output is not None:
            self.output.halt()
        clock, ingest = getattr(self, "clock", None), getattr(self, "zone_ingest", None)
        if clock is not None:
            clock.shutdown()
        if ingest is not None:
            ingest.shutdown()
        if self.loop is not None:
            self.loop.shutdown()
        for kind, entity in self._built:
            getattr(self, ENTITIES[kind])(entity)
        if self._parameters_callback is not None:
            self.remove_on_set_parameters_callback(self._parameters_callback)
        self._built, self._parameters_callback = set(), None
        self.loop = self.output = self.clock = self.zone_ingest = None

    def fail_safe(self, reason: str) -> None:
        """The executor died: no setpoint after this, ERROR said (spin_node then exits)."""
        if self.output is not None:
            self.output.halt()
        if getattr(self, "clock", None) is not None:
            self.clock.shutdown(timeout=0.0)
        self.status.publish_failure(f"stopped commanding the robot: {one_line(reason)}")

    def destroy_node(self) -> None:
        self._free()  # no setpoint while the rest shuts down
        super().destroy_node()

    def _use_configuration(self, name: str) -> None:
        if name not in self.configurations:
            raise ValueError(f"unknown configuration {name!r}; known: "
                             f"{', '.join(self.configurations)}")
        self.config = self.configurations[name]
        self.planner = ConstrainedPlanner(self.policy, self.config, self.robot)
        if not (self.realtime and self.values["planning_process"]):
            self.planner.prepare_sampling()  # plans in this process: ready before it must
        seed = self.values["noise_seed"]
        if not self.realtime:  # a fresh loop, as a fresh node would run
            self.loop = ChunkLoop.simulated(self.planner, self.zones, self.generator,
                                            noise_seed=seed, on_install=self._after_plan)
            return
        warm_up(self.planner)  # the first zone does not pay for first calls
        if self.loop is not None:
            self.loop.use_planner(self.planner)
            return
        values, lead = self.values, self.values["lead"]
        self.loop = live_chunk_loop(
            self.planner, self.zones,
            values["torch_threads"] if values["planning_process"] else None,
            values["planning_idle"], noise_seed=seed, lead=None if lead < 0 else lead,
            soft=values["prefix_soft"], rate_hz=self.rate_hz,
            wake=self.create_guard_condition(self._on_plan_ready).trigger,
            every_tick=values["replan_every_tick"],
            replan_on_zone_change=values["replan_on_zone_change"], on_install=self._after_plan)

    def _weaker(self, parameter) -> str | None:
        """Why setting `parameter` would weaken the filter, or None."""
        if parameter.name == "configuration":
            new = self.configurations.get(parameter.value)
            if new is not None and weakens(self.config, new):
                return (f"configuration {new.name!r} promises less than {self.config.name!r} "
                        f"(guarantee {new.guarantee} < {self.config.guarantee})")
            return None
        return weaker_setting(parameter.name, self.get_parameter(parameter.name).value,
                              parameter.value)

    def _on_parameters(self, parameters) -> SetParametersResult:
        if not self.values["allow_weaker_configuration"]:
            for parameter in parameters:
                reason = self._weaker(parameter)
                if reason is not None:
                    reason += "; start the node with allow_weaker_configuration:=true to allow it"
                    self.get_logger().warning(f"refused: {reason}")
                    self.changes_refused += 1
                    return SetParametersResult(successful=False, reason=reason)
        for parameter in parameters:
            if parameter.name == "configuration":
                try:
                    self._use_configuration(parameter.value)
                except ValueError as error:
                    return SetParametersResult(successful=False, reason=str(error))
                self.configuration_changes += 1
                self.get_logger().warning(f"configuration now {parameter.value!r} (guarantee "
                                          f"{self.config.guarantee})")
        return SetParametersResult(successful=True)

    # -- observations -> setpoints ------------------------------------------------------------

    def _on_observation(self, stamp: float, stamp_msg) -> None:
        step = step_of_stamp(stamp_msg, self.robot.control_hz)
        if self.realtime:  # the setpoint the clock sends from now on
            new_run = self.observations.starts_run(stamp)
            # A reset, or a participant sending old stamps: said either way (WARN).
            self.runs_restarted += self.observations.ends_run(stamp)
            if new_run:  # a reset: the run before's setpoint is never sent again, and nothing
                self.latest_stamp = None  # is sent until this run's first observation is taken
                self.output.withdraw()
            observation = self._take(stamp)
            if observation is not None:
                if new_run:  # none of the run before's plans (one in flight) goes into this
                    self.loop.reset()  # one, even where its first stamp equals the last
                self.latest_stamp = stamp_msg
                self._send(self.loop.observe(step, observation), publish=False)
            return
        if stamp == self.last_stamp:
            # The simulator re-sends an observation until answered: the answer may have been
            # lost to a subscriber not yet matched, so send it again (no new plan, no noise).
            self.output.repeat()
            return
        observation = self._take(stamp)
        if stamp < self.last_stamp or stamp == 0.0:  # the simulator was reset: a new episode
            self.loop.reset()
        self.last_stamp = stamp
        if observation is None:  # the simulator waits for an answer: the last sound setpoint
            if self.sound.last_sound is not None:
                self._send(self.sound.last_sound, stamp_msg)
            return
        started = time.perf_counter()
        setpoint = self.loop.observe(step, observation.astype(np.float32))
        planning_ms = 1000 * (time.perf_counter() - started)
        self._send(setpoint, stamp_msg)
        self._publish_status(planning_ms)

    def _take(self, stamp: float) -> np.ndarray | None:
        """The checked observation of `stamp`, with the standstill counts updated."""
        observation = self.observations.take(stamp)
        if observation is not None:
            self.standstills.observe(
                self.observations.pusher, self.observations.moved, self.zones.area_at(0),
                self.robot.pusher_radius,
                self.loop.history is not None and bool(self.loop.rows.waiting[0]))
        return observation

    def _send(self, setpoint: np.ndarray | None, stamp=None, publish: bool = True
              ) -> float | None:
        """Realtime: stamped with the newest observation's stamp by default; published by the
        clock's next tick unless `publish`."""
        stamp = self.latest_stamp if stamp is None else stamp
        return self.output.send(setpoint, stamp, self.observations.pusher, publish)

    def _on_plan_ready(self) -> None:
        """Realtime, woken by the planning worker (or a zone change): plans installed, and
        whatever is due asked for."""
        self._send(self.loop.install_results(), publish=False)

    def _after_plan(self) -> None:
        """Plans were installed (by an observation or when the worker woke the node)."""
        self.reaction.plan_installed(self.loop.knows_zones())
        self.plan_pub.publish(path_message(self.loop.chunk, self.get_clock().now().to_msg()))

    # -- zones --------------------------------------------------------------------------------

    def _zones_changed(self, received: float, within_reach: bool = False) -> None:
        """The zones in force changed (a message that came at `received`, time.monotonic()):
        in realtime the held setpoint is checked now and a safe one published at once (how long
        after: `zone_to_setpoint_ms` in the status). Not for moving zones that stayed
        `within_reach` of what the setpoint in force was checked against: it still holds, and
        the next observation is answered against them (a hand republished at 20 Hz would
        otherwise take the executor from the observations)."""
        self.reaction.zone_changed()
        self.sound.zones_changed()
        if within_reach:
            self.zone_updates_within_reach += 1
        elif self.realtime:
            self.reaction.safe_setpoint_sent(received, self._send(self.loop.zones_changed()))

    # -- status -------------------------------------------------------------------------------

    def _on_status_timer(self) -> None:
        if self.executor_realtime is None:
            # On the thread that runs the callbacks: with FIFO priority it answers a zone
            # without waiting for other processes' time slices (the planning process, started
            # before, keeps normal scheduling).
            self.executor_realtime = request_fifo(self.values["executor_priority"])
        self._publish_status(self.loop.stats.last_plan_ms)

    def _publish_status(self, planning_ms: float) -> None:
        values = {"lifecycle": self.lifecycle,
                  "configuration": self.config.name, "guarantee": self.config.guarantee,
                  "configuration_changes": self.configuration_changes,
                  "changes_refused": self.changes_refused,
                  "runs_restarted": self.runs_restarted, "mode": self.mode,
                  "zone_updates_within_reach": self.zone_updates_within_reach,
                  **self.output.status(), **self.observations.status(),
                  **self.standstills.status(self.robot.control_hz),
                  "plans": self.loop.stats.planner_calls, "planning_ms": f"{planning_ms:.1f}",
                  **self.reaction.status(), "zones": len(self.zones), **self.zone_ingest.status()}
        if self.realtime:
            values.update(loop_status(self.loop), **self.clock.status(),
                          executor_realtime=self.executor_realtime)
            values["planning_error"] = one_line(values["planning_error"] or "")
        values["zone_ids"] = ",".join(str(i) for i in self.zones.ids)
        values.update(self._nearest_zone())
        self.status.publish(values)

    def _nearest_zone(self) -> dict[str, object]:
        """The zone nearest the pusher: its id, the gap between it and the pusher's disc (px,
        negative: overlapping), its measured speed and the speed assumed of it (px/s); the
        zones measured faster than `zone_speed_bound`, the updates that showed a zone
        faster than it was assumed to move, and those that re-placed one (`ZoneMotion.jumps`)."""
        pusher = self.observations.pusher
        nearest = None if pusher is None else self.zones.nearest(pusher)
        if nearest is None:
            return {}
        zone_id, distance, speed, assumed = nearest
        return {"nearest_zone": zone_id,
                "nearest_zone_gap_px": f"{distance - self.robot.pusher_radius:.1f}",
                "nearest_zone_speed": f"{speed:.0f}",
                "nearest_zone_assumed_speed": f"{assumed:.0f}",
                "zones_over_speed_bound": ",".join(map(str, self.zones.motion.over_bound())),
                "zone_speed_exceeded": self.zones.motion.exceeded,
                "zone_jumps": self.zones.motion.jumps}
