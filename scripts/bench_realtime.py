"""Benchmark the live action filter: repeated realtime trials with zones dropped in the
pusher's path, a zone flood, and the README's trial, on an idle and on a loaded machine.

Starts sim_node and policy_node (both `mode:=realtime`) as processes in a random ROS domain, and
drives them from an rclpy client of its own (not zone_publisher). Per configuration and
condition it runs `--trials` trials, each on its own scene (seeds from 100000; a scene with no
room for a zone the pusher could still stop before is skipped and the next tried): reset, let
the policy run, drop a square zone on the waypoints the plan in force is about to execute
(placed so the pusher's disc is still outside it), watch, clear. It prints per condition:
  - the setpoint period (windows without zone events) median, and its jitter |period - 1/rate|
    p99, as sent (the policy's publish timestamps) and as received by the client;
  - the time from publishing a zone to the first moment the setpoint in force respects it
    (outside the zone grown by the pusher radius), over all trials and over the trials where
    the node changed its setpoint for the zone (its `zone_reactions` count rose), as the
    client's callback got it (setpoints are taken on a thread of the client's own, as a robot
    driver would take them), as its middleware received it, as the policy sent it, and inside
    the node;
  - setpoints within the pusher radius of the zone after that moment, and steps where the
    pusher's disc overlaps the zone (placed so that it starts outside);
  - standstills at a zone's edge, as the node counts them: with a waypoint to execute (the
    filter's: `standstill_steps`, the longest) and while waiting for a plan
    (`standstill_waiting_steps`);
  - the time from publishing a zone to the next plan the client receives, and, as the node
    counts it (`replan_latency_ms`), from its zone callback to the first plan installed that
    was planned with the zone;
then moving-zone trials (`moving_trials.py`; `--no-moving` skips them), with the first
configuration whose name ends in `_safe` (the shield): on the same scenes, after the warm-up, a
60 px square zone of one id, republished at 20 Hz stamped with the client's clock, moving at each
`--moving-speeds` (100 and 200 px/s), then removed (an empty polygon for its id):
  - crossing: straight across the pusher's position (a random heading and a sideways offset of
    up to half a side per scene), from 150 px before it to 150 px past it;
  - homing: from 150 px away (a random direction per scene), heading for the pusher's latest
    observed position for 3 s, then straight away from it for 1 s;
and prints per kind and speed, from what the client observes (the pusher as the sim reports it,
setpoints as received, the zone as it was published then): the trials with contact (the disc
overlapping the zone), the contact steps, avoidable or not (`runner.unavoidable`: no setpoint
one step before could have kept the disc out), the deepest overlap, the least separation
(centre to zone less the radius: min and median over trials), setpoints in the zone as published
30 ms before they were received, the rise of the node's `cornered_steps` and
`zone_speed_exceeded`, and the longest standstill (under 1 px a step) with the zone within
100 px (a stopped robot is not an answer). Then a 1 kHz zone flood (zones in force = last
message per id how soon after it ends; the period p99 against the same run without a flood),
and `trial` under load. "loaded" means one busy process per `--load` core, started and stopped
by this script. Prints; asserts nothing.

  scripts/bench_realtime.py --trials 20
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from live_client import Client, start_scene
from moving_trials import (
    add_moving_arguments,
    moving_configuration,
    report_moving,
    run_moving_trials,
)

from constrained_diffusion_ros.evaluation.launcher import Stack
from constrained_diffusion_ros.evaluation.live_checks import (
    disc_depth,
    respects,
    stops_outside,
    zone_in_path,
)
from constrained_diffusion_ros.paths import SOURCE_ROOT, default_model_dir
from sim_bridge import AGENT_RADIUS

ROOT = Path(__file__).resolve().parents[1]

FIRST_SEED = 100000
MAX_ATTEMPTS = 4  # scenes tried per trial asked for, at most
# Looks for room for the zone in a scene, one per control period for 2 s, before it is skipped:
# with DDPM the pusher spends most of its time held at the end of a chunk (a plan takes longer
# than a chunk lasts), and only just after a plan is installed are there waypoints ahead of it.
LOOKS = 20
FLOOD_IDS = 30  # ids cycled by the flood (the node's cap is 32)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--configurations", nargs="+",
                        default=["ddim10_r_g10_p_safe", "r_g10_p_safe"],
                        help="constraint configurations to run (r_g10_p_safe: DDPM, 100 steps)")
    parser.add_argument("--trials", type=int, default=20,
                        help="trials (with a zone dropped) per condition")
    add_condition_arguments(parser)
    parser.add_argument("--rate-hz", type=float, default=10.0, help="control rate")
    parser.add_argument("--warmup", type=float, default=2.0,
                        help="seconds of a trial before its zone is dropped")
    parser.add_argument("--watch", type=float, default=3.0,
                        help="seconds of a trial after its zone is dropped")
    parser.add_argument("--zone-size", type=float, default=40.0, help="side of the zone, px")
    parser.add_argument("--flood-hz", type=float, default=1000.0, help="0: no flood")
    parser.add_argument("--flood-seconds", type=float, default=10.0)
    parser.add_argument("--trial-flood-hz", type=float, default=0.0,
                        help="zone messages per second from a flooding process of its own "
                             "during the trials (the reaction measured under a flood); 0: none")
    parser.add_argument("--trial-flood-vertices", type=int, default=4,
                        help="vertices of each flooding zone (64, the cap: a fuzz at the caps)")
    add_moving_arguments(parser)
    parser.add_argument("--no-trial", action="store_true",
                        help="skip running `trial` in the loaded condition")
    parser.add_argument("--log-dir", default=None, help="node logs (default: a temporary one)")
    parser.add_argument("--startup-timeout", type=float, default=90.0)
    parser.add_argument("--planning-process", choices=["true", "false"], default="true",
                        help="the policy node's planning_process parameter (false: a thread)")
    parser.add_argument("--executor-priority", type=int, default=None,
                        help="the policy node's executor_priority (0: normal scheduling; "
                             "default: the node's)")
    parser.add_argument("--every-tick", action="store_true",
                        help="the policy node with replan_every_tick:=true")
    parser.add_argument("--view", action="store_true",
                        help="also run view_node with a Foxglove WebSocket client subscribed "
                             "to every channel it serves")
    return parser


@dataclass
class Condition:
    """Everything measured in one condition (one configuration, idle or loaded)."""

    periods: list[float] = field(default_factory=list)  # s, as received by the client
    sent_periods: list[float] = field(default_factory=list)  # s, as published by the policy
    latencies: list[float] = field(default_factory=list)  # s, every trial
    reacted: list[float] = field(default_factory=list)  # s, trials whose held setpoint was unsafe
    # s, zone published -> the policy sent the first safe setpoint (its own source timestamp,
    # free of the client's receiving), in the trials where it changed its setpoint
    reacted_sent: list[float] = field(default_factory=list)
    # s, the same to when the client's middleware received it (its reception timestamp, before
    # the client's executor took it)
    reacted_delivered: list[float] = field(default_factory=list)
    in_node: list[float] = field(default_factory=list)  # s, the node's zone_to_setpoint_ms
    replans: list[float] = field(default_factory=list)  # s, zone published -> next plan received
    # s, the node's replan_latency_ms: its zone callback -> the first plan installed that was
    # planned with the zone (inf: none within the watch)
    knowing: list[float] = field(default_factory=list)
    # s, every setpoint: the client's callback after its middleware received it (what this
    # client's own executor adds to "received")
    callback_delays: list[float] = field(default_factory=list)
    inside_after: int = 0
    inside_zone: int = 0  # of those, in the zone itself
    nearest_after: float = float("inf")  # px, the closest of them came to the zone
    overlap_steps: int = 0
    overlap_px: float = 0.0  # the deepest overlap of the disc
    # The same in trials whose zone lay across the way of a setpoint the node had already sent
    # when the zone was published (the client had not received it when it placed the zone): a
    # race no filter can win, not counted above.
    raced_steps: int = 0
    raced_px: float = 0.0
    trials: int = 0
    skipped: int = 0  # no place for a zone the disc was outside of


def print_timeline(client: Client, shape: shapely.Polygon, published: float, seed: int,
                   first_setpoint: int, first_pusher: int) -> None:
    """An overlap trial's events around the zone, in ms from its publishing, as the client got
    them: the pusher (step, position, disc depth in the zone) and the setpoints (distance of
    the point to the zone less the pusher radius: negative is inside the grown zone)."""
    events = [(t, f"pusher step {step:4d} ({p[0]:6.1f}, {p[1]:6.1f}) depth "
                  f"{disc_depth(shape, p):6.2f} px")
              for t, step, p in client.pushers[max(0, first_pusher):]]
    events += [(s.received, f"  setpoint ({s.point[0]:6.1f}, {s.point[1]:6.1f}) clear "
                            f"{shape.distance(shapely.Point(*s.point)) - AGENT_RADIUS:6.2f} px")
               for s in client.setpoints[max(0, first_setpoint - 3):]]
    print(f"\n  overlap in scene {seed}; zone {list(shape.exterior.coords)[:4]} published at 0:")
    for t, text in sorted(events):
        if -400 <= 1000 * (t - published) <= 1500:
            print(f"    {1000 * (t - published):7.1f} ms  {text}")


def periods_between(client: Client, start: float, stop: float) -> tuple[list[float], list[float]]:
    """Setpoint periods in a window of arrival times: as the client received them, and as the
    policy sent them (the publisher's own timestamps, free of the client's scheduling)."""
    chosen = [s for s in list(client.setpoints) if start <= s.received <= stop]
    return (list(np.diff([s.received for s in chosen])),
            list(np.diff([s.sent for s in chosen])))


def run_trial(client: Client, index: int, seed: int, args: argparse.Namespace,
              result: Condition) -> None:
    begin = start_scene(client, seed)
    client.spin_for(args.warmup)
    for _ in range(LOOKS):  # the pusher may be held or near the plan's end: look again
        placed = len(client.setpoints)  # the listener's thread keeps appending
        held = client.setpoints[placed - 1].point
        (_, step_before, before), (_, step, pusher) = client.pushers[-2:]
        moved = (pusher - before) / max(1, step - step_before)
        vertices = zone_in_path(client.plan, held, pusher, moved, args.zone_size)
        if vertices is not None:
            break
        client.spin_for(1.0 / args.rate_hz)
    else:
        result.skipped += 1
        return
    shape = shapely.Polygon(vertices)
    n_setpoints, n_pushers = len(client.setpoints), len(client.pushers)
    reactions = int(client.status.get("zone_reactions", 0))
    published, published_wall = time.monotonic(), time.time()
    client.publish_zone(1000 + index, vertices)
    client.spin_for(args.watch)  # (the diagnostics come every 0.5 s: the reaction is in)
    after = client.setpoints[n_setpoints:]  # a copy: the listener keeps appending
    # The node reacted if it changed its held setpoint because of the zone (its own count);
    # else the setpoint it held when the zone came already respected it.
    reacted = int(client.status.get("zone_reactions", 0)) > reactions
    first_index = next((i for i, s in enumerate(after) if respects(shape, s.point)), None)
    first = None if first_index is None else after[first_index].received
    if not reacted and respects(shape, held):
        first = published
    result.trials += 1
    result.replans.append(next((t for t in client.plan_times if t > published), float("inf"))
                          - published)
    knowing = float(client.status.get("replan_latency_ms", "nan")) / 1000
    result.knowing.append(knowing if np.isfinite(knowing) else float("inf"))
    latency = float("inf") if first is None else first - published
    result.latencies.append(latency)
    if reacted:
        result.reacted.append(latency)
        for stamp, kept in (("sent", result.reacted_sent),
                            ("delivered", result.reacted_delivered)):
            kept.append(float("inf") if first_index is None
                        else getattr(after[first_index], stamp) - published_wall)
        result.in_node.append(float(client.status.get("zone_to_setpoint_ms", "nan")) / 1000)
    later = [s.point for s in after if first is not None and s.received > first]
    result.inside_after += sum(not respects(shape, p) for p in later)
    result.inside_zone += sum(shape.contains(shapely.Point(*p)) for p in later)
    result.nearest_after = min([result.nearest_after,
                                *(shape.distance(shapely.Point(*p)) for p in later)])
    depths = [disc_depth(shape, p)
              for _, _, p in client.pushers[n_pushers:]]
    # Sent before the zone was published, unknown to its placement (those that came while it
    # was placed too): one that heads into it runs into the zone before any answer can.
    unseen = [s.point for s in client.setpoints[placed:] if s.sent < published_wall]
    raced = any(not stops_outside(shape, pusher, moved, point) for point in unseen)
    if raced:
        result.raced_steps += sum(depth > 0 for depth in depths)
        result.raced_px = max([result.raced_px, *depths])
    else:
        result.overlap_steps += sum(depth > 0 for depth in depths)
        result.overlap_px = max([result.overlap_px, *depths])
    if max(depths, default=0.0) > 0:
        print_timeline(client, shape, published, seed, n_setpoints, n_pushers - 3)
    settled = max(published + 0.3, (first or published) + 1.0 / args.rate_hz)
    for start, stop in ((begin + 0.5, published), (settled, time.monotonic())):
        received, sent = periods_between(client, start, stop)
        result.periods += received
        result.sent_periods += sent
    client.call(client.clear, client.Trigger.Request(), "clear zones")


def flood(client: Client, args: argparse.Namespace) -> None:
    """`--flood-hz` zone messages for `--flood-seconds`, small squares along the bottom edge,
    ids cycling; then how long until the policy shows exactly the last message per id."""
    rng = np.random.default_rng(0)
    client.reset_to(FIRST_SEED)
    client.spin_for(2.0)
    start = time.monotonic()
    client.spin_for(args.flood_seconds)
    quiet, quiet_sent = periods_between(client, start, time.monotonic())
    last: dict[int, np.ndarray] = {}
    counters = ("zone_messages", "zones_refused", "zone_batches")
    before = {key: int(client.status.get(key, 0)) for key in counters}
    sent, flood_start = 0, time.monotonic()
    period = 1.0 / args.flood_hz
    while time.monotonic() - flood_start < args.flood_seconds:
        due = int((time.monotonic() - flood_start) / period) + 1
        while sent < due:
            zone_id = 2000 + sent % FLOOD_IDS
            x = rng.uniform(20, 480)
            last[zone_id] = np.array([[x, 496], [x + 12, 496], [x + 12, 508], [x, 508]])
            client.publish_zone(zone_id, last[zone_id])
            sent += 1
        client.executor.spin_once(timeout_sec=0)
    ended, ended_wall = time.monotonic(), time.time()
    flooded, flooded_sent = periods_between(client, flood_start, ended)
    expected = shapely.union_all([shapely.Polygon(v) for v in last.values()])

    def caught_up() -> bool:  # the policy's markers show the union of the last messages
        # (to 0.01 px: zone messages carry float32 vertices)
        return client.markers is not None and \
            shapely.hausdorff_distance(client.markers[2], expected) < 0.01

    try:
        client.spin_until(caught_up, 60.0, "the zones in force to equal the last messages")
        sent_lag = 1000 * max(0.0, client.markers[1] - ended_wall)
        received_lag = 1000 * max(0.0, client.markers[0] - ended)
        caught = (f"sent by the policy {sent_lag:.0f} ms after the flood ended, received "
                  f"{received_lag:.0f} ms after (0: before it ended; markers go out at most "
                  f"once per tick)")
    except RuntimeError:
        caught = "not within 60 s"
    client.spin_for(0.5)
    during = {key: int(client.status.get(key, 0)) - before[key] for key in counters}
    print(f"  flood: {sent} messages in {ended - flood_start:.1f} s ({FLOOD_IDS} ids); zones in "
          f"force = last message per id {caught}; the policy counted {during['zone_messages']} "
          f"of them, {during['zones_refused']} refused, in {during['zone_batches']} batches")
    for what, calm, flooding in (("sent", quiet_sent, flooded_sent),
                                 ("received", quiet, flooded)):
        print(f"  setpoint period p99 ({what}): {1000 * np.percentile(calm, 99):.1f} ms "
              f"without the flood, {1000 * np.percentile(flooding, 99):.1f} ms during it")
    client.call(client.clear, client.Trigger.Request(), "clear zones")


FLOODER = """
import sys, time
import numpy as np, rclpy
from geometry_msgs.msg import PolygonInstanceStamped
from msg_schemas import NAMESPACE, TOPICS, qos_profile
from msg_schemas.conversions import zone_message
domain, hz, vertices, ids = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
rclpy.init(domain_id=domain)
node = rclpy.create_node("bench_flooder", namespace=NAMESPACE)
publisher = node.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                  qos_profile(TOPICS["zones"], "publisher"))
angles = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
ring = 6.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
rng, sent, start = np.random.default_rng(0), 0, time.monotonic()
while True:
    due = int((time.monotonic() - start) * hz) + 1
    while sent < due:
        centre = (rng.uniform(20, 490), rng.uniform(496, 506))
        publisher.publish(zone_message(2000 + sent % ids, ring + centre,
                                       node.get_clock().now().to_msg()))
        sent += 1
    time.sleep(max(0.0, start + sent / hz - time.monotonic()))
"""


@contextlib.contextmanager
def flooding(domain_id: int, hz: float, vertices: int) -> Iterator[None]:
    """A process of its own publishing `hz` zone messages a second (FLOOD_IDS ids, regular
    polygons of `vertices` vertices along the bottom edge) while the block runs."""
    if hz <= 0:
        yield
        return
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, "-c", FLOODER, str(domain_id), str(hz),
                                str(vertices), str(FLOOD_IDS)], env=environment)
    try:
        yield
    finally:
        process.kill()
        process.wait()


def report(name: str, result: Condition, nominal: float) -> None:
    latency = np.array(result.latencies)
    reacted = np.array(result.reacted)

    def ms(values: np.ndarray) -> str:
        finite = values[np.isfinite(values)]
        never = f"; never: {len(values) - len(finite)}" if len(finite) < len(values) else ""
        if len(finite) == 0:
            return "n/a" + never
        return (f"median {1000 * np.median(finite):.1f}, p99 "
                f"{1000 * np.percentile(finite, 99):.1f}, max {1000 * np.max(finite):.1f} ms"
                + never)

    print(f"  {name}: {result.trials} trials ({result.skipped} skipped: no room for the zone)")
    for what, values in (("sent", result.sent_periods), ("received", result.periods)):
        periods = np.array(values)
        if len(periods) == 0:
            print(f"    setpoint period ({what}): no periods measured")
            continue
        jitter = np.abs(periods - nominal)
        print(f"    setpoint period ({what}) median {1000 * np.median(periods):.1f} ms over "
              f"{len(periods)} periods; jitter p99 {1000 * np.percentile(jitter, 99):.1f} ms, "
              f"max {1000 * np.max(jitter):.1f} ms")
    print(f"    zone published -> setpoint in force respects it: {ms(latency)}")
    print(f"    ... in the {len(reacted)} trials where the node changed its setpoint for the "
          f"zone: {ms(reacted)}")
    print(f"    ... the same, to when the policy sent it (its source timestamp): "
          f"{ms(np.array(result.reacted_sent))}; to when the client's middleware received it "
          f"(its reception timestamp): {ms(np.array(result.reacted_delivered))}; inside the "
          f"node (zone callback -> sent): {ms(np.array(result.in_node))}")
    print(f"    zone published -> the next plan received (every trial): "
          f"{ms(np.array(result.replans))}; in the node, zone callback -> the first plan "
          f"installed that knows the zone: {ms(np.array(result.knowing))}")
    print(f"    the client's own executor: its callback after its middleware had a setpoint "
          f"(every setpoint): {ms(np.array(result.callback_delays))}")
    print(f"    setpoints within the pusher radius of the zone after that (0.5 px tolerance): "
          f"{result.inside_after} ({result.inside_zone} in the zone itself; the nearest "
          f"{result.nearest_after:.2f} px from it); steps with the pusher's disc in the zone: "
          f"{result.overlap_steps}" + (f" (deepest {result.overlap_px:.2f} px)"
                                       if result.overlap_steps else "")
          + (f"; and {result.raced_steps} (deepest {result.raced_px:.2f} px) in trials whose "
             f"zone was published across the way of a setpoint already sent (the client had not "
             f"received it when it placed the zone: a race no filter can win)"
             if result.raced_steps else ""))


def cpu_times() -> np.ndarray:
    """(steal, total) CPU time of the machine so far, in clock ticks (Linux; zeros elsewhere)."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
    except (OSError, ValueError):
        return np.zeros(2)
    return np.array([fields[7] if len(fields) > 7 else 0, sum(fields[:8])])


def add_condition_arguments(parser: argparse.ArgumentParser) -> None:
    """--conditions and --load, as every live benchmark takes them."""
    parser.add_argument("--conditions", nargs="+", default=["idle", "loaded"],
                        choices=["idle", "loaded"], help="machine conditions to run")
    parser.add_argument("--load", type=int, default=1,
                        help="busy processes (one core each) in the loaded condition")


@contextlib.contextmanager
def background_load(count: int) -> Iterator[None]:
    """`count` busy processes (one core each) while the block runs, killed after it."""
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for process in load:
            process.kill()
            process.wait()


@contextlib.contextmanager
def watching(stack: Stack, on: bool) -> Iterator[dict[str, int]]:
    """view_node on a free port and a WebSocket client (a thread) subscribed to every channel
    it serves, counting what it receives, while the trials run; nothing if not `on`."""
    counts = {"frames": 0, "bytes": 0}
    if not on:
        yield counts
        return
    import json
    import socket

    from websockets.sync.client import connect

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    stack.start("view_node", port=port)
    stop = threading.Event()

    def client() -> None:
        deadline = time.monotonic() + 60
        while not stop.is_set() and time.monotonic() < deadline:
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                             max_size=None)
                break
            except OSError:
                time.sleep(0.2)
        else:
            return
        with ws:
            subscribed = 0
            while not stop.is_set():
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op["op"] == "advertise":
                        subscriptions = [{"id": subscribed + k + 1, "channelId": c["id"]}
                                         for k, c in enumerate(op["channels"])]
                        subscribed += len(subscriptions)
                        ws.send(json.dumps({"op": "subscribe",
                                            "subscriptions": subscriptions}))
                    continue
                counts["frames"] += 1
                counts["bytes"] += len(frame)

    thread = threading.Thread(target=client, daemon=True)
    thread.start()
    try:
        yield counts
    finally:
        stop.set()
        thread.join(5)


def run_condition(args: argparse.Namespace, loaded: bool) -> None:
    label = f"loaded ({args.load} busy process(es))" if loaded else "idle"
    print(f"\n== {label}, {os.cpu_count()} cores, {args.rate_hz:g} Hz ==", flush=True)
    with background_load(args.load if loaded else 0):
        for index, configuration in enumerate(args.configurations):
            base = Path(args.log_dir or tempfile.mkdtemp(prefix="bench_realtime_"))
            log_dir = base / f"{label[:6]}_{configuration}"
            log_dir.mkdir(parents=True, exist_ok=True)
            stack = Stack("bench_realtime", log_dir)
            client = Client(stack)
            try:
                stack.start("sim_node", seed=FIRST_SEED, mode="realtime",
                               rate_hz=args.rate_hz, autostart=False)
                extra = {} if args.executor_priority is None else {
                    "executor_priority": args.executor_priority}
                if args.every_tick:
                    extra["replan_every_tick"] = True
                stack.start("policy_node", model=args.model, configuration=configuration,
                               mode="realtime", rate_hz=args.rate_hz,
                               planning_process=args.planning_process == "true", **extra)
                client.spin_until(client.discovered, args.startup_timeout,
                                  "the nodes to discover each other")
                result = Condition()
                before = cpu_times()
                attempt = 0  # scenes without room for a zone are skipped; the next seed is tried
                with flooding(stack.domain_id, args.trial_flood_hz,
                              args.trial_flood_vertices), \
                        watching(stack, args.view) as viewed:
                    while result.trials < args.trials and attempt < MAX_ATTEMPTS * args.trials:
                        run_trial(client, attempt, FIRST_SEED + attempt, args, result)
                        attempt += 1
                        print(".", end="", flush=True)
                print()
                if args.view:
                    print(f"  (view_node served the trials to a client subscribed to everything:"
                          f" {viewed['frames']} messages, {viewed['bytes'] / 1e6:.1f} MB)")
                if args.trial_flood_hz > 0:
                    print(f"  (the trials ran beside a flood of {args.trial_flood_hz:g} zone "
                          f"messages a second, {FLOOD_IDS} ids of {args.trial_flood_vertices} "
                          f"vertices)")
                steal, total = cpu_times() - before
                result.callback_delays = [s.called - s.delivered for s in client.setpoints]
                report(configuration, result, 1.0 / args.rate_hz)
                print(f"    CPU time taken by the hypervisor (steal) during the trials: "
                      f"{100 * steal / max(total, 1):.1f}%")
                print("    node: " + ", ".join(f"{key} {client.status.get(key, '?')}" for key in (
                    "planning_ms", "plans", "plans_dropped", "plans_cancelled", "held_steps",
                    "late_steps", "ticks_missed", "ticks_withheld", "observations_late",
                    "tick_late_p99_ms", "clock_realtime", "executor_realtime",
                    "planning_priority")))
                print("    standstills at a zone's edge (the node's count: 5+ steps under 0.5 px "
                      "with a zone within 5 px of the disc), with a waypoint to execute: "
                      + ", ".join(f"{key} {client.status.get(key, '?')}"
                                  for key in ("standstill_steps", "standstill_longest_s"))
                      + "; while waiting for a plan: standstill_waiting_steps "
                      + str(client.status.get("standstill_waiting_steps", "?")))
                if configuration == moving_configuration(args):
                    report_moving(configuration,
                                  run_moving_trials(client, args, FIRST_SEED, start_scene))
                if index == 0 and args.flood_hz > 0:
                    flood(client, args)
            finally:
                client.close()
                stack.close()
        if loaded and not args.no_trial:
            started = time.monotonic()
            done = subprocess.run([sys.executable, "-m", "constrained_diffusion_ros.evaluation"
                                   ".trial", "--output",
                                   str(Path(tempfile.mkdtemp(prefix="trial_")) / "trial")],
                                  capture_output=True, text=True, cwd=ROOT)
            tail = (done.stdout + done.stderr).strip().splitlines()[-1:]
            print(f"  trial under load: exit {done.returncode} after "
                  f"{time.monotonic() - started:.0f} s; {' '.join(tail)}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.trials < 1 or args.rate_hz <= 0 or (args.moving_trials or 1) < 1 \
            or min(args.moving_speeds) <= 0:
        print("bench_realtime: --trials, --moving-trials, --moving-speeds and --rate-hz must be "
              "positive", file=sys.stderr)
        return 2
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    checkout = Path(__file__).resolve().parents[1]
    if checkout != SOURCE_ROOT:  # the nodes would run the package imported, not this checkout
        print(f"bench_realtime: this script is in {checkout}, but the package it runs is "
              f"{SOURCE_ROOT}'s; to measure this checkout: PYTHONPATH={checkout}",
              file=sys.stderr)
    print(f"realtime benchmark: model {args.model}, configurations {args.configurations}")
    try:
        for condition in args.conditions:
            run_condition(args, loaded=condition == "loaded")
    except KeyboardInterrupt:
        print("interrupted; node processes stopped", file=sys.stderr)
        return 130
    except RuntimeError as error:
        print(f"bench_realtime: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
