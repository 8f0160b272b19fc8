"""trial: one recorded, constrained PushT trial, every node in its own process.

Starts the recorder, the simulator (lockstep), the zone publisher and the policy node, as a
launch file would, in a ROS domain of its own; waits until they have discovered each other;
resets the scene to the seed; lets the policy act for the requested number of control steps;
waits until the bag holds every step and every topic the trial heard (a warning names what it
still lacks after RECORDING_GRACE_S); stops every process cleanly; prints score and violations
(and fails, naming it, if the policy said on /diagnostics that its plug-in zone check failed);
and leaves, in the output directory, the rosbag2 (MCAP) bag with the trial's metadata, a strip
of frames (PNG, like the paper's Fig. 1) and an animated GIF.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from constrained_diffusion_ros.cli import ArgumentParser, positive_int, run_command
from constrained_diffusion_ros.evaluation.launcher import Stack
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.recording.bags import (
    by_topic,
    read_timed_messages,
    read_unfinished,
    trial_steps,
)
from msg_schemas import OPTIONAL_NODES, SERVICES, TOPICS
from msg_schemas.conversions import point_of, pose2d_of, step_of_stamp, zones_shown
from sim_bridge import CONTROL_HZ

if TYPE_CHECKING:  # torch and shapely come with these: imported once the arguments are read
    from constrained_diffusion_ros.evaluation.rollout import RolloutLog

# One torch thread for the policy node: on a two-core machine a second thread makes an idle
# trial no faster, and beside any other load it fights that load for the cores, more than
# doubling the trial's time.
POLICY_THREADS = 1
# How long after the last step the trial waits for the bag to hold everything it heard: DDS
# resends a reliable message its reader missed after the writer's next heartbeat (every 3 s by
# Fast DDS's default).
RECORDING_GRACE_S = 10.0
# ROS 2's "safe" domain ids on Linux ("The ROS_DOMAIN_ID" in the ROS 2 docs): DDS allows up to
# 232, but above 101 the ports of a domain's participants run into Linux's ephemeral ports
# (32768 on), and a trial starts five participants; above 232 DDS has no ports for it at all.
DOMAIN_IDS = range(0, 102)
MAX_KEEPOUT_CELL = 512.0  # px: the zone publisher's keepout_resolution range is [0, 512]


def domain_id(text: str) -> int:
    """A ROS domain id the trial's nodes can all use (DOMAIN_IDS)."""
    value = int(text)
    if value not in DOMAIN_IDS:
        raise argparse.ArgumentTypeError(f"{text} is not a ROS domain id in "
                                         f"{DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1}")
    return value


def seconds(text: str) -> float:
    """A finite, positive number of seconds (a NaN would never time out)."""
    value = float(text)
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text} is not a positive, finite number of seconds")
    return value


def cell_size(text: str) -> float:
    """A keep-out cell width the zone publisher takes: 0 (polygons), or from a mask as many
    cells a side as the caps allow (`MaskCaps.cells`) up to MAX_KEEPOUT_CELL. (Imported here,
    when an argument is parsed: `--help` stays instant.)"""
    from constrained_diffusion_ros.zones.grid import MaskCaps

    value = float(text)
    side_cells = math.isqrt(MaskCaps.cells)
    finest = MAX_KEEPOUT_CELL / side_cells
    if not (value == 0.0 or finest <= value <= MAX_KEEPOUT_CELL):  # NaN too
        raise argparse.ArgumentTypeError(f"{text} is not 0 or a cell width in [{finest:g}, "
                                         f"{MAX_KEEPOUT_CELL:g}] px")
    return value


def scene_seed(text: str) -> int:
    """A seed the simulator takes (its parameter seed is non-negative)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is not a non-negative seed")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser("trial", __doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="center_0.2",
                        help="zones from config/scenarios.yaml ('none' for no zones)")
    parser.add_argument("--configuration", default="r_g10_p_safe",
                        help="constraint configuration from the configurations file")
    parser.add_argument("--configurations-file",
                        default=str(config_dir() / "configurations.yaml"),
                        help="YAML of constraint configurations the policy node reads")
    parser.add_argument("--seed", type=scene_seed, default=100000, help="PushT scene seed")
    parser.add_argument("--steps", type=positive_int, default=200,
                        help="control (action) steps")
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--output", default=None,
                        help="trial directory (default trials/<scenario>_<configuration>_<seed>);"
                             " must not exist yet")
    parser.add_argument("--scenarios-file", default=str(config_dir() / "scenarios.yaml"),
                        help="YAML of scenarios (zones, keep-out grids or plug-in checks)")
    parser.add_argument("--keepout-grid", type=cell_size, default=0.0, metavar="PX",
                        help="publish the scenario as a keep-out mask (nav2's convention) with "
                             "cells PX wide instead of as polygon zones; 0: polygons")
    parser.add_argument("--timeout", type=seconds, default=600.0,
                        help="seconds before the trial gives up")
    parser.add_argument("--domain-id", type=domain_id, default=None,
                        help="ROS domain of the trial's nodes, 0..101 (default: a random one in "
                             "1..100, so no other node is heard; set it to watch the trial "
                             "live)")
    return parser


class TrialListener:
    """What the trial hears on its client node: the pusher, block and setpoint of every step
    (`received`, by control step), every contract topic heard at all (`heard`: the bag must
    hold each before the nodes stop), the zones the policy shows (`zones_in_force`, one count
    per markers message) and what it said of a failed plug-in check (`zone_check_errors`)."""

    KEPT = (("pusher", "pusher"), ("block_pose", "block"), ("setpoint", "setpoint"))

    def __init__(self, node) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from visualization_msgs.msg import MarkerArray

        from msg_schemas import qos_profile

        self.received: dict[str, dict[int, object]] = {kind: {} for _, kind in self.KEPT}
        self.heard: set[str] = set()
        self.zones_in_force: list[int] = []
        self.zone_check_errors: list[str] = []
        for topic, kind in self.KEPT:
            node.create_subscription(TOPICS[topic].message_class(), TOPICS[topic].name,
                                     lambda msg, kind=kind: self._keep(kind, msg),
                                     qos_profile(TOPICS[topic], "recorder"))
        for endpoint in TOPICS.values():
            node.create_subscription(endpoint.message_class(), endpoint.name,
                                     self._hear(endpoint.resolved()),
                                     qos_profile(endpoint, "recorder"), raw=True)
        node.create_subscription(MarkerArray, TOPICS["zone_markers"].name,
                                 lambda msg: self.zones_in_force.append(zones_shown(msg)),
                                 qos_profile(TOPICS["zone_markers"]))
        node.create_subscription(DiagnosticArray, TOPICS["diagnostics"].name, self._diagnosed,
                                 qos_profile(TOPICS["diagnostics"], "recorder"))

    def _hear(self, topic: str) -> Callable[[bytes], None]:
        return lambda _data: self.heard.add(topic)

    def _keep(self, kind: str, msg) -> None:
        self.received[kind][step_of_stamp(msg.header.stamp, CONTROL_HZ)] = msg

    def _diagnosed(self, msg) -> None:
        for status in msg.status:
            said = next((kv.value for kv in status.values if kv.key == "zone_check_error"), "")
            if said and said not in self.zone_check_errors:
                self.zone_check_errors.append(said)

    def complete(self, steps: int) -> bool:
        """Every step's pusher and block (0 .. steps) and setpoint (0 .. steps - 1) arrived:
        topics arrive in no fixed order."""
        received = self.received
        return (all(t in received["pusher"] and t in received["block"] for t in range(steps + 1))
                and all(t in received["setpoint"] for t in range(steps)))


def checked_output(args: argparse.Namespace):
    """The scenario asked for (None: none) and the trial's new output directory, after what
    the policy node would refuse is refused here first: one line, no directory made."""
    from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
    from constrained_diffusion_ros.policy.weights import load_policy

    scenarios = load_scenarios(args.scenarios_file)
    scenario = scenarios.get(args.scenario) if args.scenario != "none" else None
    if args.scenario != "none" and scenario is None:
        raise ValueError(f"unknown scenario {args.scenario!r}; known: {', '.join(scenarios)}")
    if args.keepout_grid and (scenario is None or scenario.plugin):
        raise ValueError("--keepout-grid needs a scenario of zones (not a plug-in)")
    configurations = load_configurations(args.configurations_file)
    if args.configuration not in configurations:
        raise ValueError(f"unknown configuration {args.configuration!r}; known: "
                         f"{', '.join(configurations)}")
    load_policy(args.model)  # config and weights (truncated, NaN) checked before any process
    output = Path(args.output or f"trials/{args.scenario}_{args.configuration}_{args.seed}")
    if output.exists():
        raise ValueError(f"{output} exists already; choose another --output (trials are never "
                         "overwritten)")
    output.mkdir(parents=True)
    return scenario, output


def start_nodes(stack: Stack, scenario, args: argparse.Namespace, output: Path,
                metadata_file: Path) -> str | None:
    """Recorder, simulator (lockstep, waiting for its reset), the scenario's zones (a topic's
    publisher, or the policy's plug-in check) and the policy node, left unconfigured; the
    topic the zones come on (None: no zone topic)."""
    stack.start("recorder", output=output / "bag", metadata_file=metadata_file)
    stack.start("sim_node", seed=args.seed, mode="lockstep", max_steps=args.steps,
                autostart=False)
    plug_in, zone_topic = {}, None
    if scenario is not None and scenario.plugin:
        plug_in = {"restricted_area": scenario.plugin["class"],
                   "restricted_area_parameters": yaml.safe_dump(
                       scenario.plugin.get("parameters") or {}, default_flow_style=True)}
    elif scenario is not None:
        zone_topic = TOPICS["keepout_mask" if args.keepout_grid else "zones"].name
        stack.start("zone_publisher", scenario=args.scenario,
                    scenarios_file=args.scenarios_file, keepout_resolution=args.keepout_grid)
    stack.start("policy_node", threads=POLICY_THREADS, torch_threads=POLICY_THREADS,
                model=args.model, configuration=args.configuration,
                configurations_file=args.configurations_file, autostart=False, **plug_in)
    return zone_topic


def subscribed(node, topic: str) -> bool:
    """Every node the contract names as a subscriber of `topic` (but the optional ones) is in
    the graph, counted without `node`'s own subscriptions."""
    own = sum(s.topic_name == TOPICS[topic].resolved() for s in node.subscriptions)
    needed = set(TOPICS[topic].subscribers) - set(OPTIONAL_NODES)
    return node.count_subscribers(TOPICS[topic].name) - own >= len(needed)


def discovered(node, zone_topic: str | None, zone_kind: str) -> bool:
    """The graph has every node the trial needs: setpoints published and taken, the pusher
    taken, and the zones' publisher and subscriber."""
    ready = (node.count_publishers(TOPICS["setpoint"].name) >= 1
             and subscribed(node, "setpoint") and subscribed(node, "pusher"))
    if zone_topic is not None:
        ready &= node.count_publishers(zone_topic) >= 1 and subscribed(node, zone_kind)
    return ready


def publishers_matched(stack: Stack, recorded_first: list[str]) -> bool:
    """Both sides of discovery have matched (the nodes' logs say so): the recorder the
    publishers the trial's figures come from, and the simulator's and the policy's publishers
    every subscriber the graph shows. The graph alone is not enough: a recorder that matches a
    publisher late misses what it sent before (a short trial's first setpoints), and a
    publisher that has not matched the recorder yet sends the first setpoint past the bag."""
    logs = stack.logs
    return (all(matched(logs["recorder"], topic, "publisher") >= 1 for topic in recorded_first)
            and all(matched(logs[name], topic, "subscriber")
                    >= stack.node.count_subscribers(TOPICS[topic].name)
                    for name, topic in (("policy_node", "setpoint"), ("sim_node", "pusher"),
                                        ("sim_node", "block_pose"))))


def run_trial(args: argparse.Namespace) -> dict:
    from std_srvs.srv import Trigger

    scenario, output = checked_output(args)
    metadata_file = output / "trial.json"
    metadata = {"scenario": args.scenario, "configuration": args.configuration,
                "seed": args.seed, "steps": args.steps, "model": str(args.model),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    metadata_file.write_text(json.dumps(metadata, indent=2))

    stack = Stack("trial", output, args.domain_id)
    listener = TrialListener(stack.node)
    reset = stack.node.create_client(Trigger, SERVICES["reset"].name)
    deadline = time.monotonic() + args.timeout
    zone_kind = "keepout_mask" if args.keepout_grid else "zones"
    try:
        zone_topic = start_nodes(stack, scenario, args, output, metadata_file)
        stack.transition("configure", deadline=deadline)  # loads the policy and subscribes
        stack.transition("activate", deadline=deadline)  # setpoints from its first answer on
        # The zones too: a recorder that matches the zone publisher after its latched history
        # can still reach it records no zone message.
        recorded_first = ["setpoint", "pusher", "block_pose"] + ([zone_kind] if zone_topic
                                                                 else [])
        stack.wait_for(lambda: discovered(stack.node, zone_topic, zone_kind) and
                       reset.service_is_ready(), "the nodes to discover each other",
                       deadline=deadline, period_s=0.05)
        stack.wait_for(lambda: publishers_matched(stack, recorded_first),
                       "the publishers and the recorder to match", deadline=deadline,
                       period_s=0.05)
        if scenario is not None:  # the policy echoes the zones in force as markers, one each
            expected = len(scenario.polygons_at(0))  # (a mask's pieces: at least one)
            shown = listener.zones_in_force
            stack.wait_for(lambda: bool(shown) and (shown[-1] >= 1 if args.keepout_grid
                                                    else shown[-1] == expected),
                           "the policy to hold the scenario's zones", deadline=deadline,
                           period_s=0.05)
        stack.call(reset, Trigger.Request(), "the simulator's reset", deadline=deadline)
        stack.wait_for(lambda: listener.complete(args.steps), f"{args.steps} control steps",
                       deadline=deadline, period_s=0.05)
        results = trial_results(listener.received, scenario, args)
        metadata["results"] = results
        metadata_file.write_text(json.dumps(metadata, indent=2))

        # The bag can still lack a topic after the last step: a reliable writer resends a sample
        # its reader missed only after its next heartbeat, so the nodes stop only once the bag
        # holds everything the trial heard, or after RECORDING_GRACE_S.
        until = time.monotonic() + RECORDING_GRACE_S
        while ((missing := bag_lacks(output / "bag", listener.heard, listener.received))
               and time.monotonic() < until and not stack.failed()):
            stack.executor.spin_once(timeout_sec=0.1)
        if missing:  # the results stand (from the messages the trial received): said, kept
            print(f"trial: warning: the bag still lacks {', '.join(missing)} "
                  f"{RECORDING_GRACE_S:.0f} s after the last step (see {output}/recorder.log)",
                  file=sys.stderr)
        if listener.zone_check_errors:  # the first fault, in the bag's metadata too
            metadata["zone_check_error"] = listener.zone_check_errors[0]
            metadata_file.write_text(json.dumps(metadata, indent=2))
    finally:
        try:
            for name in ("policy_node", "zone_publisher", "sim_node"):
                stack.processes.stop(name)
            time.sleep(0.5)  # let the recorder take the last messages
        finally:
            stack.close()
    make_figures(output, scenario, args, listener.received)
    return metadata


def bag_lacks(bag: Path, heard: set[str], received: dict[str, dict[int, object]]) -> list[str]:
    """What a bag being recorded lacks of the topics (full names) and of the trial's messages
    by control step (`received`: kind -> step -> message) that the trial heard itself."""
    messages = read_unfinished(bag)
    steps = trial_steps(messages)
    return sorted(heard - set(messages)) + [
        f"{kind} of steps {sorted(received[kind].keys() - steps[kind].keys())}"
        for kind in received if received[kind].keys() - steps[kind].keys()]


def matched(log: Path, topic: str, side: str) -> int:
    """The last count of `side`s ("publisher" or "subscriber") a node logged as matched on the
    contract topic (node_support.spin.log_matches); 0 before any."""
    counts = re.findall(rf"{re.escape(TOPICS[topic].resolved())}: (\d+) {side}\(s\) matched",
                        log.read_text())
    return int(counts[-1]) if counts else 0


def trial_log(received: dict, seed: int, steps: int) -> RolloutLog:
    """The recorded trial as a RolloutLog, so its metrics come from the evaluation's code."""
    from constrained_diffusion_ros.evaluation.rollout import RolloutLog
    from sim_bridge import coverage

    for kind, last in (("pusher", steps), ("block", steps), ("setpoint", steps - 1)):
        missing = sorted(set(range(last + 1)) - set(received[kind]))
        if missing:
            raise RuntimeError(f"the trial lacks {kind} messages for steps {missing[:5]}")

    states = np.array([np.concatenate([point_of(received["pusher"][t]),
                                       pose2d_of(received["block"][t])])
                       for t in range(steps + 1)])
    commanded = np.array([point_of(received["setpoint"][t]) for t in range(steps)])
    cov = coverage(states[1:, 2:5])
    return RolloutLog([seed], commanded[None], states[None], cov[None])


def trial_results(received: dict, scenario, args: argparse.Namespace) -> dict:
    from constrained_diffusion_ros.evaluation.runner import cell_metrics

    log = trial_log(received, args.seed, args.steps)
    if scenario is None:
        return {"s": float(log.best_score[0]), "final_score": float(log.final_score[0])}
    return cell_metrics(log, np.array([0]), scenario)


def make_figures(output: Path, scenario, args: argparse.Namespace, received: dict) -> None:
    """PNG strip and GIF, drawn from the bag as recorded; from the messages received live if
    the bag lacks some (said on stderr: the trial's results stand, the bag is incomplete). The
    view's scene (scene.mcap) from a bag that could be read."""
    import imageio.v3 as iio

    from constrained_diffusion_ros.evaluation.report import plot_frames
    from constrained_diffusion_ros.evaluation.scenarios import Scenario
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT
    from constrained_diffusion_ros.view.replay import write_scene
    from sim_bridge import render_scene

    recorded = None
    try:
        recorded = read_timed_messages(output / "bag")  # read once: figures and scene
        log = trial_log(trial_steps(by_topic(recorded)), args.seed, args.steps)
    except (RuntimeError, ValueError) as error:  # steps missing, or a bag not closed
        print(f"trial: warning: the bag is incomplete ({error}); figures drawn from the "
              f"messages received live", file=sys.stderr)
        log = trial_log(received, args.seed, args.steps)
    shown = scenario or Scenario("none", "no zones", ())  # a scenario without zones
    plot_frames(log, 0, shown, output / "frames.png",
                f"{args.configuration} on {shown.label}, seed {args.seed}")
    frames = [render_scene(log.states[0, t], size=256, zones=shown.polygons_at(t),
                           setpoint=log.commanded[0, min(t, args.steps - 1)])
              for t in range(0, args.steps + 1, 2)]
    iio.imwrite(output / "trial.gif", np.stack(frames), duration=100, loop=0)
    if recorded is not None:  # the live view's scene, for the Foxglove app
        inflating = {name for name, config in
                     load_configurations(args.configurations_file).items() if config.inflate}
        write_scene(recorded, output / "scene.mcap", inflating, PUSHT_ROBOT.pusher_radius)


TRIAL_FAILED = 1  # the nodes failed or timed out: not a bad argument


def run(args: argparse.Namespace) -> int:
    try:
        metadata = run_trial(args)
    except RuntimeError as error:
        print(f"trial: failed: {error}", file=sys.stderr)
        return TRIAL_FAILED
    except KeyboardInterrupt:
        print("trial: interrupted; processes stopped, bag closed", file=sys.stderr)
        return 130
    results = metadata["results"]
    output = Path(args.output or f"trials/{args.scenario}_{args.configuration}_{args.seed}")
    print(f"trial {args.scenario} / {args.configuration} / seed {args.seed}: best score "
          f"{results['s']:.3f}, final score {results['final_score']:.3f}, setpoints inside "
          f"zones r = {results.get('r', 0):.0f}, body overlaps r_body = "
          f"{results.get('r_body', 0):.0f}")
    print(f"wrote {output}/bag (rosbag2, MCAP), {output}/frames.png, {output}/trial.gif, "
          f"{output}/scene.mcap (the scene for the Foxglove app)")
    if "zone_check_error" in metadata:  # the pusher was stopped: the score is not the policy's
        print(f"trial: failed: the policy's plug-in zone check failed during the trial: "
              f"{metadata['zone_check_error']}", file=sys.stderr)
        return TRIAL_FAILED
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command(run, build_parser().parse_args(argv), "trial")


if __name__ == "__main__":
    sys.exit(main())
