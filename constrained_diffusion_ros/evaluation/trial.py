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
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from constrained_diffusion_ros.cli import ArgumentParser, positive_int, run_command
from constrained_diffusion_ros.evaluation.launcher import NodeProcesses, random_domain_id
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.recording.bags import (
    by_topic,
    read_timed_messages,
    read_unfinished,
    trial_steps,
)
from msg_schemas import NAMESPACE, OPTIONAL_NODES, SERVICES, TOPICS
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


def run_trial(args: argparse.Namespace) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, PoseStamped
    from lifecycle_msgs.srv import ChangeState
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
    from constrained_diffusion_ros.policy.weights import load_policy
    from msg_schemas import qos_profile
    from msg_schemas.node_support.spin import spin_until

    scenarios = load_scenarios(args.scenarios_file)
    scenario = scenarios.get(args.scenario) if args.scenario != "none" else None
    if args.scenario != "none" and scenario is None:
        raise ValueError(f"unknown scenario {args.scenario!r}; known: {', '.join(scenarios)}")
    if args.keepout_grid and (scenario is None or scenario.plugin):
        raise ValueError("--keepout-grid needs a scenario of zones (not a plug-in)")
    # What the policy node would refuse, refused here first: one line, no output directory.
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
    metadata_file = output / "trial.json"
    metadata = {"scenario": args.scenario, "configuration": args.configuration,
                "seed": args.seed, "steps": args.steps, "model": str(args.model),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    metadata_file.write_text(json.dumps(metadata, indent=2))

    domain_id = random_domain_id() if args.domain_id is None else args.domain_id
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("trial", namespace=NAMESPACE, context=context)
    received: dict[str, dict[int, object]] = {"pusher": {}, "block": {}, "setpoint": {}}

    def keep(kind: str):
        def callback(msg) -> None:
            received[kind][step_of_stamp(msg.header.stamp, CONTROL_HZ)] = msg
        return callback

    for topic, kind, msg_type in (("pusher", "pusher", PointStamped),
                                  ("block_pose", "block", PoseStamped),
                                  ("setpoint", "setpoint", PointStamped)):
        node.create_subscription(msg_type, TOPICS[topic].name, keep(kind),
                                 qos_profile(TOPICS[topic], "recorder"))
    # Every contract topic heard: the bag must hold each of them before the nodes stop.
    heard: set[str] = set()

    def hear(topic: str):
        return lambda _data: heard.add(topic)

    for endpoint in TOPICS.values():
        node.create_subscription(endpoint.message_class(), endpoint.name,
                                 hear(endpoint.resolved()), qos_profile(endpoint, "recorder"),
                                 raw=True)
    zones_in_force: list[int] = []
    node.create_subscription(
        MarkerArray, TOPICS["zone_markers"].name,
        lambda msg: zones_in_force.append(zones_shown(msg)),
        qos_profile(TOPICS["zone_markers"]))
    zone_check_errors: list[str] = []  # what the policy said of its plug-in check, if it failed

    def diagnosed(msg) -> None:
        for status in msg.status:
            said = next((kv.value for kv in status.values if kv.key == "zone_check_error"), "")
            if said and said not in zone_check_errors:
                zone_check_errors.append(said)

    node.create_subscription(DiagnosticArray, TOPICS["diagnostics"].name, diagnosed,
                             qos_profile(TOPICS["diagnostics"], "recorder"))
    reset = node.create_client(Trigger, SERVICES["reset"].name)
    lifecycle = node.create_client(ChangeState, SERVICES["change_state"].name)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    children = NodeProcesses(output, domain_id)
    deadline = time.monotonic() + args.timeout
    try:
        _, recorder_log = children.start("recorder", output=output / "bag",
                                         metadata_file=metadata_file)
        _, sim_log = children.start("sim_node", seed=args.seed, mode="lockstep",
                                    max_steps=args.steps, autostart=False)
        plug_in, zone_topic = {}, None  # a plug-in check goes to the policy, zones to topics
        if scenario is not None and scenario.plugin:
            plug_in = {"restricted_area": scenario.plugin["class"],
                       "restricted_area_parameters": yaml.safe_dump(
                           scenario.plugin.get("parameters") or {}, default_flow_style=True)}
        elif scenario is not None:
            zone_topic = TOPICS["keepout_mask" if args.keepout_grid else "zones"].name
            children.start("zone_publisher", scenario=args.scenario,
                           scenarios_file=args.scenarios_file,
                           keepout_resolution=args.keepout_grid)
        _, policy_log = children.start("policy_node", threads=POLICY_THREADS,
                                       torch_threads=POLICY_THREADS, model=args.model,
                                       configuration=args.configuration,
                                       configurations_file=args.configurations_file,
                                       autostart=False, **plug_in)

        def wait_for(condition, what: str) -> None:
            spin_until(executor, condition, deadline=deadline, period_s=0.05,
                       failed=children.failed, what=what)

        def transition(label: str) -> None:
            """The policy node through a lifecycle transition, as a lifecycle manager asks."""
            wait_for(lifecycle.service_is_ready, "the policy node's lifecycle services")
            request = ChangeState.Request()
            request.transition.label = label
            answer = lifecycle.call_async(request)
            wait_for(answer.done, f"the policy node to {label}")
            if not answer.result().success:
                raise ValueError(f"the policy node could not {label} (see {policy_log})")

        transition("configure")  # loads the policy and subscribes
        transition("activate")  # sends setpoints from its first answer on

        def subscribed(topic: str) -> bool:
            """Every node the contract names as a subscriber of `topic` (but the optional
            ones) is in the graph (counted without this node's own subscriptions)."""
            own = sum(s.topic_name == TOPICS[topic].resolved() for s in node.subscriptions)
            needed = set(TOPICS[topic].subscribers) - set(OPTIONAL_NODES)
            return node.count_subscribers(TOPICS[topic].name) - own >= len(needed)

        def discovered() -> bool:
            ready = (node.count_publishers(TOPICS["setpoint"].name) >= 1 and subscribed("setpoint")
                     and subscribed("pusher") and reset.service_is_ready())
            if zone_topic is not None:
                ready &= node.count_publishers(zone_topic) >= 1 and \
                    subscribed("keepout_mask" if args.keepout_grid else "zones")
            return ready

        def publishers_matched() -> bool:
            """Both sides of discovery have matched (the nodes' logs say so): the recorder the
            publishers the trial's figures come from, and the simulator's and the policy's
            publishers every subscriber the graph shows. The graph alone is not enough: a
            recorder that matches a publisher late misses what it sent before (a short trial's
            first setpoints), and a publisher that has not matched the recorder yet sends the
            first setpoint past the bag."""
            return (all(matched(recorder_log, topic, "publisher") >= 1 for topic in recorded_first)
                    and all(matched(log, topic, "subscriber") >= node.count_subscribers(
                        TOPICS[topic].name) for log, topic in ((policy_log, "setpoint"),
                                                               (sim_log, "pusher"),
                                                               (sim_log, "block_pose"))))

        # The zones too: a recorder that matches the zone publisher after its latched history
        # can still reach it records no zone message.
        recorded_first = ["setpoint", "pusher", "block_pose"]
        if zone_topic is not None:
            recorded_first.append("keepout_mask" if args.keepout_grid else "zones")

        wait_for(discovered, "the nodes to discover each other")
        wait_for(publishers_matched, "the publishers and the recorder to match")
        if scenario is not None:  # the policy echoes the zones in force as markers, one each
            expected = len(scenario.polygons_at(0))  # (a mask's pieces: at least one)

            def holds_zones() -> bool:
                shown = zones_in_force[-1] if zones_in_force else 0
                return shown >= 1 if args.keepout_grid else shown == expected

            wait_for(holds_zones, "the policy to hold the scenario's zones")
        future = reset.call_async(Trigger.Request())
        wait_for(future.done, "the simulator's reset")
        def complete() -> bool:  # topics arrive in no fixed order: wait for every one
            observed = range(args.steps + 1)
            return (all(t in received["pusher"] and t in received["block"] for t in observed)
                    and all(t in received["setpoint"] for t in range(args.steps)))

        wait_for(complete, f"{args.steps} control steps")
        results = trial_results(received, scenario, args)
        metadata["results"] = results
        metadata_file.write_text(json.dumps(metadata, indent=2))

        # The bag can still lack a topic after the last step: a reliable writer resends a sample
        # its reader missed only after its next heartbeat, so the nodes stop only once the bag
        # holds everything the trial heard, or after RECORDING_GRACE_S.
        until = time.monotonic() + RECORDING_GRACE_S
        while ((missing := bag_lacks(output / "bag", heard, received))
               and time.monotonic() < until and not children.failed()):
            executor.spin_once(timeout_sec=0.1)
        if missing:  # the results stand (from the messages the trial received): said, kept
            print(f"trial: warning: the bag still lacks {', '.join(missing)} "
                  f"{RECORDING_GRACE_S:.0f} s after the last step (see {output}/recorder.log)",
                  file=sys.stderr)
        if zone_check_errors:  # the first fault, in the bag's metadata too
            metadata["zone_check_error"] = zone_check_errors[0]
            metadata_file.write_text(json.dumps(metadata, indent=2))
    finally:
        for name in ("policy_node", "zone_publisher", "sim_node"):
            children.stop(name)
        time.sleep(0.5)  # let the recorder take the last messages
        children.stop_all()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    make_figures(output, scenario, args, received)
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
    contract topic (msg_schemas.node_support.spin.log_matches); 0 before any."""
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
