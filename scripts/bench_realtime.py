"""Benchmark the policy in a realtime loop: setpoint timing, and replanning after a zone change.

Starts sim_node (realtime, stepping on its own timer) and policy_node as processes in a random
ROS domain, listens for a while, and reports:
  - the setpoint period (arrival to arrival) median and the 99th percentile of its jitter,
    |period - 1 / rate|, beside the same for the sim's observations, and the policy's response
    time (observation arrival -> setpoint arrival, same stamp);
  - after a zone published mid-run by this script: when the policy showed it (zone markers),
    the policy's own `replan_latency_ms` (zone arrival -> new plan), and the time from
    publishing the zone to the first setpoint that is not a waypoint of the plan in force.
By default the zone is a square around the tail of the plan in force when it is published, so
the rest of that chunk violates it and the policy must replan at once. Prints; asserts nothing.

  scripts/bench_realtime.py --seconds 20 --configuration ddim10_r_g10_p_safe
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from constrained_diffusion_ros.evaluation.launcher import (  # noqa: E402
    NodeProcesses,
    random_domain_id,
)
from constrained_diffusion_ros.paths import config_dir, default_model_dir  # noqa: E402
from msg_schemas import SERVICES, TOPICS, qos_profile  # noqa: E402
from msg_schemas.conversions import (  # noqa: E402
    path_of,
    point_of,
    step_of_stamp,
    zone_message,
    zones_shown,
)
from sim_bridge import CONTROL_HZ  # noqa: E402

ZONE_ID = 900  # far from the ids scenarios use
MAX_POINT_GAP = 1e-3  # px: a setpoint this close to a waypoint of the old plan comes from it


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--configuration", default="ddim10_r_g10_p_safe",
                        help="constraint configuration name")
    parser.add_argument("--configurations-file",
                        default=str(config_dir() / "configurations.yaml"),
                        help="YAML of constraint configurations")
    parser.add_argument("--seconds", type=float, default=20.0,
                        help="how long to observe setpoints")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="sim control rate")
    parser.add_argument("--seed", type=int, default=100000, help="PushT scene seed")
    parser.add_argument("--zone-at", type=float, default=None,
                        help="seconds into the run to publish the zone (default: half way)")
    parser.add_argument("--zone", default="auto",
                        help="'x1,y1;x2,y2;...' in px, or 'auto': a square around the tail of "
                             "the plan in force")
    parser.add_argument("--zone-size", type=float, default=80.0, help="side of the auto zone, px")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS domain (default: a random one, so nothing else is heard)")
    parser.add_argument("--log-dir", default=None,
                        help="where the nodes' logs go (default: a temporary directory)")
    parser.add_argument("--load", type=int, default=0,
                        help="busy processes (one core each) run beside the nodes, stopped at "
                             "the end: measure a busy machine")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads of each node process")
    parser.add_argument("--startup-timeout", type=float, default=60.0,
                        help="seconds to wait for the nodes to start and discover each other")
    return parser


def parse_zone(text: str) -> np.ndarray:
    return np.array([[float(c) for c in pair.split(",")] for pair in text.split(";")
                     if pair.strip()])


def auto_zone(plan: np.ndarray, side: float) -> np.ndarray:
    """A square around the last quarter of a plan's waypoints, inside the workspace."""
    centre = np.clip(plan[-len(plan) // 4:].mean(axis=0), side / 2, 512 - side / 2)
    half = side / 2
    return centre + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])


def stats_ms(values: np.ndarray) -> str:
    if len(values) == 0:
        return "n/a"
    return (f"median {np.median(values):.1f} ms, p99 {np.percentile(values, 99):.1f} ms, "
            f"max {np.max(values):.1f} ms")


def period_report(label: str, arrivals: list[float], nominal_ms: float) -> None:
    periods = 1000 * np.diff(np.asarray(arrivals))
    if len(periods) == 0:
        print(f"{label}: fewer than two arrivals")
        return
    jitter = np.abs(periods - nominal_ms)
    print(f"{label} period: median {np.median(periods):.1f} ms over {len(periods)} periods; "
          f"jitter |period - {nominal_ms:.0f} ms|: median {np.median(jitter):.1f} ms, "
          f"p99 {np.percentile(jitter, 99):.1f} ms, max {np.max(jitter):.1f} ms")


def run(args: argparse.Namespace) -> int:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from geometry_msgs.msg import PointStamped, PolygonInstanceStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    domain_id = args.domain_id if args.domain_id is not None else random_domain_id()
    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="bench_realtime_"))
    log_dir.mkdir(parents=True, exist_ok=True)
    nominal_ms = 1000.0 / args.rate_hz
    zone_at = args.seconds / 2 if args.zone_at is None else args.zone_at
    print(f"background load: {args.load} busy process(es) on {os.cpu_count()} cores")
    print(f"realtime benchmark: model {args.model}, configuration {args.configuration}, "
          f"{args.rate_hz:g} Hz, {args.seconds:g} s, ROS domain {domain_id}, logs in {log_dir}")

    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("bench_realtime", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    children = NodeProcesses(log_dir, domain_id, threads=args.threads)

    def now() -> float:
        return time.monotonic()

    setpoints: list[tuple[float, int, np.ndarray]] = []  # arrival, step, point
    observations: dict[int, float] = {}  # step -> first arrival
    observation_arrivals: list[float] = []
    plans: list[tuple[float, np.ndarray]] = []
    statuses: list[tuple[float, dict[str, str]]] = []
    markers: list[tuple[float, int]] = []  # arrival, zones shown

    def on_setpoint(msg) -> None:
        setpoints.append((now(), step_of_stamp(msg.header.stamp, CONTROL_HZ), point_of(msg)))

    def on_pusher(msg) -> None:
        step = step_of_stamp(msg.header.stamp, CONTROL_HZ)
        if step not in observations:
            observations[step] = now()
            observation_arrivals.append(observations[step])

    def subscribe(key: str, msg_type, callback) -> None:
        node.create_subscription(msg_type, TOPICS[key].name, callback, qos_profile(TOPICS[key]))

    subscribe("setpoint", PointStamped, on_setpoint)
    subscribe("pusher", PointStamped, on_pusher)
    subscribe("plan", PathMsg, lambda msg: plans.append((now(), path_of(msg))))
    subscribe("policy_status", DiagnosticStatus, lambda msg: statuses.append(
        (now(), {kv.key: kv.value for kv in msg.values})))
    subscribe("zone_markers", MarkerArray, lambda msg: markers.append((now(), zones_shown(msg))))
    zone_pub = node.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                     qos_profile(TOPICS["zones"], "publisher"))
    reset = node.create_client(Trigger, SERVICES["reset"].name)

    def spin_until(condition, timeout: float, what: str) -> None:
        deadline = now() + timeout
        while not condition():
            failure = children.failed()
            if failure:
                raise RuntimeError(failure)
            if now() > deadline:
                raise RuntimeError(f"timed out waiting for {what}")
            executor.spin_once(timeout_sec=0.01)

    def spin_for(seconds: float) -> None:
        deadline = now() + seconds
        while now() < deadline:
            failure = children.failed()
            if failure:
                raise RuntimeError(failure)
            executor.spin_once(timeout_sec=0.005)

    try:
        children.start("sim_node", seed=args.seed, mode="realtime", rate_hz=args.rate_hz,
                       autostart=False)
        children.start("policy_node", model=args.model,
                       configuration=args.configuration,
                       configurations_file=args.configurations_file)
        started = now()
        spin_until(lambda: reset.service_is_ready()
                   and all(s.get_publisher_count() >= 1 for s in node.subscriptions)
                   and zone_pub.get_subscription_count() >= 1
                   and node.count_subscribers(TOPICS["pusher"].name) >= 2,
                   args.startup_timeout, "the nodes to discover each other")
        print(f"nodes up and discovered after {now() - started:.1f} s")
        future = reset.call_async(Trigger.Request())
        spin_until(future.done, 10.0, "the sim's reset")
        spin_until(lambda: len(setpoints) > 0, 30.0, "the first setpoint")
        begin = now()
        spin_for(zone_at)

        # The zone, published mid-run.
        if args.zone == "auto":
            spin_until(lambda: len(plans) > 0, 10.0, "a plan")
            vertices = auto_zone(plans[-1][1], args.zone_size)
        else:
            vertices = parse_zone(args.zone)
        old_plan = plans[-1][1] if plans else np.zeros((0, 2))
        n_setpoints, n_statuses, n_markers = len(setpoints), len(statuses), len(markers)
        msg = zone_message(ZONE_ID, vertices, node.get_clock().now().to_msg())
        published = now()
        zone_pub.publish(msg)
        spin_for(max(0.0, args.seconds - (now() - begin)))
    finally:
        children.stop_all()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)

    # ---- report
    window = [s for s in setpoints if begin <= s[0]]
    steps = [s[1] for s in window]
    missed = (max(steps) - min(steps) + 1 - len(set(steps))) if steps else 0
    print(f"setpoints: {len(window)} in {args.seconds:g} s, {missed} steps without one")
    period_report("setpoint", [s[0] for s in window], nominal_ms)
    period_report("sim observation", [t for t in observation_arrivals if t >= begin], nominal_ms)
    response = np.array([1000 * (t - observations[step]) for t, step, _ in window
                         if step in observations])
    print(f"policy response (observation arrival -> setpoint arrival): {stats_ms(response)}")
    planning = np.array([float(v["planning_ms"]) for t, v in statuses if t >= begin])
    print(f"policy planning_ms per setpoint (status): {stats_ms(planning)}")

    zone_text = ";".join(f"{x:.0f},{y:.0f}" for x, y in vertices)
    print(f"zone {ZONE_ID} published at {published - begin:.1f} s: {zone_text}")
    shown = [t for t, count in markers[n_markers:] if count >= 1]
    print("  zone markers from the policy: " + (f"{1000 * (shown[0] - published):.1f} ms after "
                                                 "publishing" if shown else "never"))
    before = statuses[n_statuses - 1][1].get("replan_latency_ms") if n_statuses else None
    latency = next((v["replan_latency_ms"] for _, v in statuses[n_statuses:]
                    if v.get("zones") == "1" and v.get("replan_latency_ms") != before), None)
    print(f"  policy_status replan_latency_ms (zone arrival -> new plan): "
          f"{latency + ' ms' if latency else 'none reported'}")
    after = setpoints[n_setpoints:]
    off_plan = next(((t, step) for t, step, point in after if len(old_plan) == 0
                     or np.min(np.linalg.norm(old_plan - point, axis=1)) > MAX_POINT_GAP), None)
    if off_plan is None:
        print("  no setpoint off the old plan after the zone")
    else:
        t, step = off_plan
        print(f"  first setpoint off the old plan: {1000 * (t - published):.1f} ms after "
              f"publishing (step {step}, {sum(s[0] < t for s in after)} old-plan setpoints "
              "before it)")
    import shapely

    zone_shape = shapely.Polygon(vertices)
    inside = sum(zone_shape.contains(shapely.Point(*point)) for t, _, point in after
                 if off_plan is not None and t >= off_plan[0])
    print(f"  setpoints inside the zone from then on: {inside}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Ctrl-C and SIGTERM both end the run with KeyboardInterrupt, so the node processes are
    # stopped either way (SIGINT explicitly too: a shell starts background jobs ignoring it).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    # A known background load, started and stopped here: one busy core per process.
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.load)]
    try:
        return run(args)
    except KeyboardInterrupt:
        print("interrupted; node processes stopped", file=sys.stderr)
        return 130
    except RuntimeError as error:
        print(f"bench_realtime: {error}", file=sys.stderr)
        return 1
    finally:
        for process in load:
            process.kill()
            process.wait()


if __name__ == "__main__":
    sys.exit(main())
