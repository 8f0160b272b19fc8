"""The policy node's parameters (declared with descriptors; `--help` and the README's table are
made from them) and the plug-in area they name.

Importable without torch or rclpy, so that `policy_node --help` answers at once: the core's
defaults the table shows are written out below, and the core is imported where the values are
used."""

from __future__ import annotations

import pickle
from typing import TYPE_CHECKING

from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.runtime.os_scheduling import CLOCK_PRIORITY, EXECUTOR_PRIORITY
from msg_schemas.text import one_line
from node_support.parameters import Param
from sim_bridge.scene import AGENT_RADIUS, CONTROL_HZ, K_P, K_V, SIM_HZ, WORKSPACE_SIZE

if TYPE_CHECKING:
    from constrained_diffusion_ros.planning.robot import RobotModel
    from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea
    from constrained_diffusion_ros.zones.live import LiveZones

MODES = ("lockstep", "realtime")
ROBOT_FIELDS = ("pusher_radius", "kp", "kv", "control_hz", "physics_hz")  # and workspace

# The core's defaults, written out: the modules that own them import torch. The owner of each is
# named; test/unit/test_help_imports.py keeps them equal (the robot's too: pusht.PUSHT_ROBOT,
# read here from the scene's facts as pusht.py reads them).
DEVICES = "cpu, cuda or cuda:N"  # policy.device.DEVICES
RUNTIMES = ("torch", "onnxruntime")  # policy.runtime.RUNTIMES
DEFAULT_THRESHOLD = 65  # zones.grid.DEFAULT_THRESHOLD
MASK_PIECES, MASK_VERTICES, MASK_CELLS = 32, 1024, 4096 * 4096  # zones.grid.MaskCaps()
DEFAULT_MAX_ZONES, DEFAULT_MAX_VERTICES = 32, 64  # zones.live
DEFAULT_SPEED_BOUND, HEADROOM = 300.0, 1.5  # zones.motion

PARAMETERS = (
    Param("model", str(default_model_dir()), "policy directory (config.json + "
          "model.safetensors)", read_only=True),
    Param("configuration", "r_g10_p_safe", "constraint configuration, a name from the "
          "configurations file; settable at run time to one that promises as much (guarantee "
          "body > setpoint > none)"),
    Param("allow_weaker_configuration", False, "allow run-time changes that weaken the filter "
          "(a configuration that promises less, a shorter zone_lifetime, a higher "
          "keepout_threshold): off, any participant on the network could turn it down",
          read_only=True),
    Param("configurations_file", str(config_dir() / "configurations.yaml"),
          "constraint configurations YAML", read_only=True),
    Param("noise_seed", 0, "seed of the denoising noise (deterministic trials)", read_only=True,
          low=0),
    Param("zone_lifetime", 0.0, "s; a zone not re-published within it expires; 0: never",
          low=0.0),
    Param("autostart", True, "configure and activate at start, as nav2's lifecycle manager "
          "does with autostart; false: the node waits, unconfigured, for its lifecycle services "
          "(change_state: configure, then activate)", read_only=True),
    Param("mode", "lockstep", "lockstep: one setpoint per observation, planned in the "
          "callback; realtime: one per tick of rate_hz, planned in the background",
          read_only=True, choices=MODES),
    Param("rate_hz", 10.0, "realtime: setpoints per second", read_only=True, low=0.1,
          high=1000.0),
    Param("lead", -1, "realtime: steps before the chunk runs out at which the next plan "
          "starts; -1: from the measured planning time", read_only=True, low=-1),
    Param("replan_every_tick", False, "realtime: ask for a new plan at every observation that "
          "finds none on its way (the waypoints due before it arrives held fixed), not only "
          "lead steps before the chunk runs out; planning then runs all the time",
          read_only=True),
    Param("replan_on_zone_change", True, "realtime: ask for a new plan at every change of "
          "the zones, so that a plan that knows them follows within one planning time; false: "
          "only when they refuse the setpoint held or lie on the rest of the chunk",
          read_only=True),
    Param("prefix_soft", 4, "realtime: waypoints after the committed ones drawn toward the "
          "chunk in force; -1: no inpainting", read_only=True, low=-1),
    Param("executor_watchdog_s", 0.5, "realtime: the clock sends no setpoint while the "
          "executor, which answers zones, has not run for this long (the robot holds its last "
          "target); 0: never withhold", read_only=True, low=0.0),
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
    Param("zone_speed_bound", DEFAULT_SPEED_BOUND, "px/s: the speed a zone is assumed able to "
          "move at, in any direction, once an update (its id republished elsewhere) has shown "
          "it moving; the shield keeps the disc out of all it can reach before the robot "
          "reacts (docs/moving_zones.md). A zone never seen moving stands still; one measured "
          "faster than this: WARN, the guarantee does not hold for it", read_only=True,
          low=0.0),
    Param("zone_speed_headroom", HEADROOM, "a moving zone is assumed able to move at this many "
          "times the fastest it was measured at between two updates (at least 50 px/s, at "
          "most zone_speed_bound); 0: at zone_speed_bound, whatever it was measured at (the "
          "ISO 13855 reading, the strictest and the slowest task)", read_only=True, low=0.0),
    Param("max_zones", DEFAULT_MAX_ZONES, "zones in force at most; more are refused",
          read_only=True, low=1),
    Param("max_vertices", DEFAULT_MAX_VERTICES, "vertices per zone at most", read_only=True,
          low=3),
    Param("max_mask_pieces", MASK_PIECES, "keep-out mask: pieces (separate regions) at "
          "most; a finer mask is refused", read_only=True, low=1),
    Param("max_mask_vertices", MASK_VERTICES, "keep-out mask: vertices of all its pieces "
          "at most; a finer mask is refused", read_only=True, low=4),
    Param("keepout_threshold", DEFAULT_THRESHOLD, "keep-out mask cells at or above it are "
          "restricted (nav2's occupied threshold, 0..100)", low=1, high=100),
    Param("restricted_area", "", "a plug-in check always in force: 'package.module:Class' or "
          "an entry point of group constrained_diffusion_ros.restricted_areas; empty: none",
          read_only=True),
    Param("restricted_area_parameters", "", "its keyword arguments, a YAML mapping, e.g. "
          "'{config_file: camera_zones.yaml}'", read_only=True),
    # What the planner knows of the robot (PushT's by default), read at start.
    Param("robot.pusher_radius", float(AGENT_RADIUS),
          "px; zones grown by it keep the pusher's body out", read_only=True, low=0.0),
    Param("robot.workspace", [0.0, 0.0, WORKSPACE_SIZE, WORKSPACE_SIZE],
          "px: x_min, y_min, x_max, y_max; outside counts as restricted", read_only=True),
    Param("robot.kp", float(K_P), "PD gain on position (1/s^2)", read_only=True,
          low=0.0),
    Param("robot.kv", float(K_V), "PD gain on velocity (1/s)", read_only=True,
          low=0.0),
    Param("robot.control_hz", float(CONTROL_HZ), "setpoints per second; stamps "
          "are control steps at this rate", read_only=True, low=0.1),
    Param("robot.physics_hz", float(SIM_HZ), "PD integration rate the shield "
          "predicts the pusher with", read_only=True, low=0.1),
)


def weaker_setting(name: str, old: object, new: object) -> str | None:
    """Why changing run-time parameter `name` from `old` to `new` lets more through, or None:
    zones that expire sooner (a lifetime of 1e-6 s drops every zone as it comes), keep-out
    cells that stop counting (a higher threshold)."""
    if name == "zone_lifetime" and new and (not old or new < old):
        return f"zone_lifetime {new} s lets zones expire sooner than {old or 'never'}"
    if name == "keepout_threshold" and new > old:
        return f"keepout_threshold {new} restricts fewer keep-out cells than {old}"
    return None


def robot_model(values: dict) -> RobotModel:
    """The robot the parameters describe (PushT's pusher in the observation)."""
    from constrained_diffusion_ros.planning.robot import RobotModel
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT

    return RobotModel(**{name: values[f"robot.{name}"] for name in ROBOT_FIELDS},
                      workspace=tuple(values["robot.workspace"]),
                      pusher_in_observation=PUSHT_ROBOT.pusher_in_observation)


def live_zones(values: dict, workspace: Bounds, reaction_s: float) -> LiveZones:
    """The zones in force: their caps and the plug-in area, which must pickle where a planning
    process will get it; a moving zone grown for a robot that reacts in `reaction_s`."""
    from constrained_diffusion_ros.zones.live import LiveZones

    area = plug_in_area(values["restricted_area"], values["restricted_area_parameters"],
                        workspace)
    if values["mode"] == "realtime" and values["planning_process"]:
        check_picklable(area, values["restricted_area"])
    return LiveZones(values["max_zones"], values["max_vertices"], area, workspace=workspace,
                     speed_bound=values["zone_speed_bound"],
                     speed_headroom=values["zone_speed_headroom"], reaction_s=reaction_s)


def plug_in_area(spec: str, parameters: str, workspace: Bounds) -> RestrictedArea | None:
    """The plug-in check named by the parameters, probed over `workspace`, or None;
    ValueError with one line."""
    from constrained_diffusion_ros.planning.constraint_configs import safe_yaml
    from constrained_diffusion_ros.zones.plugins import load_area

    if not spec:
        return None
    keywords = safe_yaml(parameters, "parameter restricted_area_parameters") \
        if parameters else {}
    if not isinstance(keywords, dict):
        raise ValueError(f"parameter restricted_area_parameters must be a mapping, got "
                         f"{parameters!r}")
    return load_area(spec, keywords, workspace=workspace)


def check_picklable(area: RestrictedArea | None, spec: str) -> None:
    """The planning process gets the zones by pickle: a plug-in area that cannot be pickled is
    refused at start, in one line, rather than failing every plan."""
    if area is None:
        return
    try:
        pickle.dumps(area)
    except Exception as error:
        raise ValueError(f"restricted_area {spec!r} cannot be sent to the planning process "
                         f"({one_line(error)}); set planning_process:=false") from None
