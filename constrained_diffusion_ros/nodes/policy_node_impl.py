"""The policy node itself (`policy_node` is its command, and says what it does): apart, so
that `policy_node --help` answers from the parameter table without importing torch, rclpy
or the planning core."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import State, TransitionCallbackReturn

from constrained_diffusion_ros.nodes.observation_input import ObservationInput
from constrained_diffusion_ros.nodes.policy_modes import MODES
from constrained_diffusion_ros.nodes.policy_parameters import (
    PARAMETERS,
    live_zones,
    robot_model,
    weaker_setting,
)
from constrained_diffusion_ros.nodes.policy_status import ReactionTimes, StatusReporter
from constrained_diffusion_ros.nodes.setpoint_output import SetpointOutput
from constrained_diffusion_ros.nodes.zone_clearing import ZoneClearing
from constrained_diffusion_ros.nodes.zone_ingest import ZoneIngest
from constrained_diffusion_ros.nodes.zone_markers import ZoneMarkers
from constrained_diffusion_ros.planning.chunk_loop import ChunkLoop
from constrained_diffusion_ros.planning.constraint_configs import load_configurations, weakens
from constrained_diffusion_ros.planning.liveness import StandstillCounts
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.planning.sound_setpoints import SoundSetpoints
from constrained_diffusion_ros.policy.inference import use_runtime
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.zones.grid import MaskCaps
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import path_message
from msg_schemas.text import one_line
from node_support.parameters import declare
from node_support.spin import RosLogHandler, StartupPhases, log_matches

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
        self.timing = MODES[self.mode](self)  # lockstep or realtime: how it meets time
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
            self.publish_status(self.loop.stats.last_plan_ms)
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
        self.timing = MODES[self.mode](self)  # afresh, as after a cleanup
        self.timing.tune()
        self.robot = robot_model(values)
        self.policy = load_policy(values["model"], values["device"])
        startup.mark("weights")
        runtime = values["runtime"]
        if runtime == "auto":
            runtime = self.timing.default_runtime
        self.runtime = use_runtime(self.policy, runtime)
        startup.mark(self.runtime)
        self.configurations = load_configurations(values["configurations_file"])
        self.zones = live_zones(values, self.robot.workspace, self.robot.reaction_s)
        self.generator = torch.Generator().manual_seed(values["noise_seed"])
        self.configuration_changes = 0
        self.changes_refused = 0  # run-time parameter changes refused for weakening the filter
        self.zone_updates_within_reach = 0  # moving zones' updates left to the next observation
        self._use_configuration(values["configuration"])
        startup.mark("planner and its worker")
        self._parameters_callback = self.add_on_set_parameters_callback(self._on_parameters)

        self.sound = SoundSetpoints(self.robot, self.zones)
        self.output = SetpointOutput(self, self.sound, self.timing.watchdog_s())
        self.output.pause()  # until activated
        self.plan_pub = self.create_publisher(PathMsg, TOPICS["plan"].name,
                                              qos_profile(TOPICS["plan"], "publisher"))
        log_matches(self, [self.output.publisher])  # who gets the first setpoint
        # Zones first: when a zone and an observation are ready together, the zone is taken first.
        self.zone_ingest = ZoneIngest(
            self, self.zones, self.robot.workspace,
            MaskCaps(pieces=values["max_mask_pieces"], vertices=values["max_mask_vertices"]),
            self._zones_changed, realtime=self.timing.realtime, alive=self.output.beat)
        # Markers at most once per tick in realtime, where a flood must not cost one a message.
        self.zone_markers = ZoneMarkers(self, self.zones,
                                        1.0 / self.rate_hz if self.timing.realtime else None)
        ZoneClearing(self, self.zones, lambda: self._zones_changed(time.monotonic()))
        self.observations = ObservationInput(
            self, self.robot, self.timing.observe,
            late_s=1.0 / self.rate_hz if self.timing.realtime else None)
        self.standstills = StandstillCounts()  # the pusher parked at a zone's edge
        self.reaction = ReactionTimes()
        self.timing.start()
        startup.mark("the rest")
        self.get_logger().info(
            f"{self.mode} policy from {values['model']}, configuration "
            f"{self.config.name!r}, network on {self.runtime}; start-up: {startup.text()}")

    def _free(self) -> None:
        """What configure built, stopped and destroyed (no setpoint after it starts)."""
        if self.output is not None:
            self.output.halt()
        self.timing.shutdown()
        ingest = getattr(self, "zone_ingest", None)
        if ingest is not None:
            ingest.shutdown()
        if self.loop is not None:
            self.loop.shutdown()
        for kind, entity in self._built:
            getattr(self, ENTITIES[kind])(entity)
        if self._parameters_callback is not None:
            self.remove_on_set_parameters_callback(self._parameters_callback)
        self._built, self._parameters_callback = set(), None
        self.loop = self.output = self.zone_ingest = self.zone_markers = None

    def fail_safe(self, reason: str) -> None:
        """The executor died: no setpoint after this, ERROR said (spin_node then exits)."""
        if self.output is not None:
            self.output.halt()
        self.timing.shutdown(wait=False)
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
        if self.timing.plans_here():
            self.planner.prepare_sampling()  # plans in this process: ready before it must
        self.loop = self.timing.make_loop(self.planner)

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

    def take(self, stamp: float) -> np.ndarray | None:
        """The checked observation of `stamp`, with the standstill counts updated."""
        observation = self.observations.take(stamp)
        if observation is not None:
            self.standstills.observe(
                self.observations.pusher, self.observations.moved, self.zones.area_at(0),
                self.robot.pusher_radius,
                self.loop.history is not None and bool(self.loop.rows.waiting[0]))
        return observation

    def send(self, setpoint: np.ndarray | None, stamp, publish: bool = True) -> float | None:
        """`setpoint` out, stamped `stamp` (`SetpointOutput.send`): published now if
        `publish`, else by the clock's next tick."""
        return self.output.send(setpoint, stamp, self.observations.pusher, publish)

    def after_plan(self) -> None:
        """Plans were installed (by an observation or when the worker woke the node)."""
        self.reaction.plan_installed(self.loop.knows_zones())
        self.plan_pub.publish(path_message(self.loop.chunk, self.get_clock().now().to_msg()))

    # -- zones --------------------------------------------------------------------------------

    def _zones_changed(self, received: float, within_reach: bool = False) -> None:
        """The zones in force changed (a message that came at `received`, time.monotonic()):
        in realtime the held setpoint is checked now and a safe one published at once
        (`Realtime.zones_changed`). Not for moving zones that stayed
        `within_reach` of what the setpoint in force was checked against: it still holds, and
        the next observation is answered against them (a hand republished at 20 Hz would
        otherwise take the executor from the observations)."""
        self.reaction.zone_changed()
        self.sound.zones_changed()
        if within_reach:
            self.zone_updates_within_reach += 1
        else:
            self.timing.zones_changed(received)
        self.zone_markers.changed()

    # -- status -------------------------------------------------------------------------------

    def publish_status(self, planning_ms: float) -> None:
        values = {"lifecycle": self.lifecycle,
                  "configuration": self.config.name, "guarantee": self.config.guarantee,
                  "configuration_changes": self.configuration_changes,
                  "changes_refused": self.changes_refused,
                  "runs_restarted": self.timing.runs_restarted,
                  "mode": self.mode,
                  "zone_updates_within_reach": self.zone_updates_within_reach,
                  **self.output.status(), **self.observations.status(),
                  **self.standstills.status(self.robot.control_hz),
                  "plans": self.loop.stats.planner_calls, "planning_ms": f"{planning_ms:.1f}",
                  **self.reaction.status(), "zones": len(self.zones), **self.zone_ingest.status()}
        values.update(self.timing.status())
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
