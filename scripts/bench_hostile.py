"""Benchmark the policy node against zone messages too big to read (issue 41, finding 1): the
big-message attack rerun on a realtime node, on an idle and on a loaded machine.

A zone message of a million vertices froze the node (rclpy read it vertex by vertex before the
64-vertex cap was checked) and the operator's zone published just after it was not obeyed for
seconds. The node now takes zone messages serialized and refuses those too long to read, unread
(`zones_oversized`). This script starts sim_node and policy_node (the shipped model, both
`mode:=realtime`) in a random ROS domain, drives them from an rclpy client of its own (the one of
bench_realtime.py) and runs, per condition, each attack in turn on a fresh scene with no zones:

  a  one 100k-vertex zone (1.2 MB) from a publisher of its own, then (`--gap-ms` later) the
     operator's zone from the operator's publisher;
  b  the same with one 1M-vertex zone (12 MB);
  c  a burst of 20 200k-vertex zones (2.4 MB each, one every `--burst-period` s), each
     followed `--gap-ms` later by an operator zone from the SAME publisher (DDS delivers it
     behind the big one);
  d  a 300k-vertex zone (3.6 MB) twice a second for 20 s from a second publisher while the
     operator publishes 5 zones, one every 3.9 s (at varying phases of the stream).

Every operator zone is a 30 px square on the latest setpoint the client received, under one id
(each replaces the last). It prints, per attack and condition:
  - per operator zone: the time from publishing it to the first setpoint the client received
    that respects it (outside the zone grown by the pusher radius, 15 px, with bench_realtime's
    0.5 px tolerance), and to when the policy sent that setpoint (its source timestamp);
    setpoints received inside the grown zone meanwhile (and of those, how many the policy
    sent after the zone was published: not in flight already), and after; the node's own
    `zone_to_setpoint_ms` (/diagnostics come every 0.5 s: sampled only where a status came
    between the answer and the next operator zone). A zone replaced by the next before a
    setpoint respected it (or not respected by the end of the watch) counts as unanswered;
  - the node's memory: RSS of the policy node process and its children (the planning process)
    before, the sampled peak (every 20 ms) and VmHWM (the kernel's peak, reset through
    /proc/<pid>/clear_refs when the attack starts; else the peak since start);
  - whether the node process is alive at the end and its diagnostics still come, the longest
    gap between its diagnostics during the attack, and the node's counts over the attack:
    `zones_oversized` and `zone_messages` (against the big messages sent), `zones_refused`,
    `ticks_withheld`, `violations`, `ticks_missed`; the clock's and the executor's real-time
    scheduling as the node reports it (`clock_realtime`, `executor_realtime`);
  - setpoint timing during the attack: each tick's lateness against the clock's grid of
    absolute deadlines (fitted on the quiet 2 s before the attack; a tick is the first setpoint
    the policy sent at or after its deadline, so a zone's answer, an extra setpoint, cannot
    lengthen it), p99 and max; and the longest gap between setpoints as the client received
    them.

"loaded" means `--load` busy processes (one core each) that the script starts and stops. Every
process it starts is stopped at the end, on an error and on Ctrl-C. Prints; asserts nothing.

  OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_hostile.py [--attacks a b c d]
      [--conditions idle loaded] [--repeats 3]   (about 5 minutes on 2 cores)
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from bench_realtime import add_condition_arguments, background_load
from live_client import Client

from constrained_diffusion_ros.evaluation.launcher import Stack
from constrained_diffusion_ros.evaluation.live_checks import respects, square
from constrained_diffusion_ros.paths import SOURCE_ROOT, default_model_dir
from msg_schemas import TOPICS, qos_profile
from msg_schemas.conversions import zone_message

ROOT = Path(__file__).resolve().parents[1]
FIRST_SEED = 100000
OPERATOR_ID = 7  # every operator zone (each replaces the last)
ATTACKER_ID = 900
ZONE_SIDE = 30.0  # px, the operator's square
QUIET_S = 2.0  # s of setpoints before an attack: the tick grid is fitted on them
WATCH_S = 1.5  # s watched after an attack's last message
SAMPLE_S = 0.02  # s between memory samples
GRID_SLACK_S = 0.003  # a setpoint this early for its tick's deadline still counts as the tick


@dataclass(frozen=True)
class Attack:
    key: str
    title: str
    vertices: int


ATTACKS = {a.key: a for a in (
    Attack("a", "one 100k-vertex zone", 100_000),
    Attack("b", "one 1M-vertex zone", 1_000_000),
    Attack("c", "20 x 200k, operator zone from the same publisher", 200_000),
    Attack("d", "300k at 2 Hz for 20 s, second publisher", 300_000),
)}


def zone_bytes(zone_id: int, vertices: int) -> bytes:
    """A serialized zone message of `vertices` vertices: the fail-safe test's own builder (no
    Point32 object per vertex), so the bench sends exactly the message the test sends."""
    sys.path.insert(0, str(ROOT / "test" / "ros"))
    try:
        from test_fail_safe import zone_bytes as build
    finally:
        sys.path.remove(str(ROOT / "test" / "ros"))
    return build(zone_id, vertices)


@dataclass
class OperatorZone:
    published: float  # time.monotonic()
    published_wall: float  # time.time(), the clock of the setpoints' source timestamps
    shape: shapely.Polygon
    reaction: float = float("inf")  # s, to the first respecting setpoint the client received
    reaction_sent: float = float("inf")  # s, to when the policy sent it
    inside_before: int = 0
    inside_before_late: int = 0  # of those, sent by the policy after the zone was published
    inside_after: int = 0
    in_node_ms: float = float("nan")  # the node's zone_to_setpoint_ms, if sampled


@dataclass
class Outcome:
    """One attack in one condition, over its repeats."""

    zones: list[OperatorZone] = field(default_factory=list)
    big_sent: int = 0
    deltas: dict[str, int] = field(default_factory=dict)
    rss_before_mb: float = 0.0
    rss_peak_mb: float = 0.0
    hwm_mb: float = 0.0
    hwm_reset: bool = True
    processes: int = 0  # the policy node and its children, as found when the attack started
    alive: bool = True
    diagnostics_after: bool = True
    diagnostics_gap_s: float = 0.0
    lateness: list[float] = field(default_factory=list)  # s, per tick
    longest_gap_s: float = 0.0  # s, between setpoints received
    notes: list[str] = field(default_factory=list)


COUNTED = ("zones_oversized", "zone_messages", "zones_refused", "ticks_withheld", "violations",
           "ticks_missed")


class HelpFormatter(argparse.RawDescriptionHelpFormatter,
                    argparse.ArgumentDefaultsHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--attacks", nargs="+", default=list(ATTACKS), choices=list(ATTACKS),
                        help="attacks to run, in this order (a-d above)")
    add_condition_arguments(parser)
    parser.add_argument("--repeats", type=int, default=3,
                        help="times each attack is run per condition (each on a fresh scene)")
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--configuration", default="ddim10_r_g10_p_safe")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="control rate")
    parser.add_argument("--gap-ms", type=float, default=10.0,
                        help="ms from a big message to the operator zone after it (a, b, c)")
    parser.add_argument("--burst-period", type=float, default=0.25,
                        help="s between the big messages of attack c (an operator zone not "
                             "answered before the next replaces it counts as unanswered)")
    parser.add_argument("--stream-seconds", type=float, default=20.0,
                        help="s of attack d's stream (twice a second)")
    parser.add_argument("--log-dir", default=None, help="node logs (default: a temporary one)")
    parser.add_argument("--startup-timeout", type=float, default=90.0)
    return parser


# -- the node's process tree ------------------------------------------------------------------

def process_tree(pid: int) -> list[int]:
    """`pid` and its descendants (Linux /proc), those still there."""
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        try:
            for task in Path(f"/proc/{current}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return found


def status_kb(pid: int, key: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def tree_kb(pid: int, key: str) -> int:
    return sum(status_kb(p, key) for p in process_tree(pid))


def reset_peaks(pid: int) -> bool:
    """Resets VmHWM of the tree (writing 5 to clear_refs); False where that is not allowed."""
    done = True
    for p in process_tree(pid):
        try:
            Path(f"/proc/{p}/clear_refs").write_text("5")
        except OSError:
            done = False
    return done


class MemorySampler:
    """The summed VmRSS of a process tree every SAMPLE_S on a thread, its peak kept."""

    def __init__(self, pid: int) -> None:
        self.pid, self.peak_kb = pid, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak_kb = max(self.peak_kb, tree_kb(self.pid, "VmRSS"))
            self._stop.wait(SAMPLE_S)

    def stop(self) -> int:
        self._stop.set()
        self._thread.join(5.0)
        return self.peak_kb


# -- the bench ----------------------------------------------------------------------------------

class Bench:
    """The nodes of one condition and the client that attacks and watches them."""

    def __init__(self, args: argparse.Namespace, log_dir: Path) -> None:
        self.args, self.log_dir = args, log_dir
        self.stack: Stack | None = None
        self.client: Client | None = None
        self.diagnostics: list[tuple[float, dict[str, str]]] = []  # (monotonic, values)
        self.starts = 0

    def start(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self.starts += 1
        run_dir = self.log_dir / f"run{self.starts}"
        run_dir.mkdir(parents=True, exist_ok=True)
        self.stack = Stack("bench_hostile", run_dir)
        self.client = client = Client(self.stack)
        self.diagnostics = []

        def on_status(msg) -> None:
            for status in msg.status:
                if status.name.endswith("policy_node"):
                    self.diagnostics.append((time.monotonic(),
                                             {kv.key: kv.value for kv in status.values}))
        client.node.create_subscription(DiagnosticArray, TOPICS["diagnostics"].name, on_status,
                                        qos_profile(TOPICS["diagnostics"]))
        self.stack.start("sim_node", seed=FIRST_SEED, mode="realtime",
                         rate_hz=self.args.rate_hz, autostart=False)
        self.stack.start("policy_node", model=self.args.model,
                         configuration=self.args.configuration, mode="realtime",
                         rate_hz=self.args.rate_hz)
        client.spin_until(client.discovered, self.args.startup_timeout,
                          "the nodes to discover each other")

    def stop(self) -> None:
        try:
            if self.client is not None:
                self.client.close()
        finally:
            if self.stack is not None:
                self.stack.close()
            self.stack = self.client = None

    @property
    def node(self):
        return self.stack.processes.processes["policy_node"]

    def spin_for(self, seconds: float) -> None:
        """Spins the client for `seconds` whether or not the nodes still run."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.client.executor.spin_once(timeout_sec=min(0.005, left))

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                return False
            self.client.executor.spin_once(timeout_sec=0.005)
        return True

    def fresh_status(self, after: float, timeout: float = 3.0) -> dict[str, str] | None:
        """The first diagnostics of the policy node received after `after` (monotonic)."""
        if self.spin_until(lambda: self.diagnostics and self.diagnostics[-1][0] > after, timeout):
            return next(v for t, v in self.diagnostics if t > after)
        return None

    def prepare(self, seed: int) -> None:
        """No zones, a fresh scene, a plan running, then QUIET_S of setpoints."""
        client = self.client
        if self.stack.failed():
            raise RuntimeError(self.stack.failed())
        client.call(client.clear, client.Trigger.Request(), "clear zones")
        client.reset_to(seed)
        begin = time.monotonic()
        client.spin_until(lambda: client.plan_time > begin and client.setpoints
                          and client.setpoints[-1].received > begin, 60.0,
                          "a plan after the reset")
        self.spin_for(QUIET_S)


def tick_grid(sent: np.ndarray, period: float) -> float:
    """The phase (s, in [0, period)) of ticks on absolute deadlines, from the sent times of a
    quiet window: a circular mean of the times modulo the period."""
    angles = 2 * np.pi * np.mod(sent, period) / period
    return float(np.angle(np.mean(np.exp(1j * angles))) % (2 * np.pi) / (2 * np.pi) * period)


def run_attack(bench: Bench, attack: Attack, payload: bytes, seed: int, outcome: Outcome) -> None:
    from geometry_msgs.msg import PolygonInstanceStamped

    args, client = bench.args, bench.client
    period = 1.0 / args.rate_hz
    gap = args.gap_ms / 1000
    bench.prepare(seed)
    quiet_start = time.monotonic() - QUIET_S
    quiet = [s.sent for s in list(client.setpoints) if s.received > quiet_start]
    phase = tick_grid(np.array(quiet), period)
    before = bench.fresh_status(time.monotonic()) or {}
    pid = bench.node.pid
    outcome.rss_before_mb = max(outcome.rss_before_mb, tree_kb(pid, "VmRSS") / 1024)
    outcome.hwm_reset &= reset_peaks(pid)
    outcome.processes = max(outcome.processes, len(process_tree(pid)))
    sampler = MemorySampler(pid)
    attacker = client.node.create_publisher(PolygonInstanceStamped, TOPICS["zones"].name,
                                            qos_profile(TOPICS["zones"], "publisher"))
    zones: list[OperatorZone] = []

    def operator(publisher) -> None:
        centre = client.setpoints[-1].point
        vertices = square(centre, ZONE_SIDE)
        message = zone_message(OPERATOR_ID, vertices, client.node.get_clock().now().to_msg())
        zones.append(OperatorZone(time.monotonic(), time.time(), shapely.Polygon(vertices)))
        publisher.publish(message)

    def big() -> None:
        attacker.publish(payload)
        outcome.big_sent += 1

    # (offset s, action): the attack's schedule
    if attack.key in ("a", "b"):
        events = [(0.0, big), (gap, lambda: operator(client.zones))]
    elif attack.key == "c":
        events = []
        for k in range(20):
            events += [(k * args.burst_period, big),
                       (k * args.burst_period + gap, lambda: operator(attacker))]
    else:
        count = round(2 * args.stream_seconds)
        events = [(k * 0.5, big) for k in range(count)]
        events += [(1.7 + 3.9 * k, lambda: operator(client.zones)) for k in range(5)
                   if 1.7 + 3.9 * k < args.stream_seconds]
    events.sort(key=lambda e: e[0])
    started, started_wall = time.monotonic(), time.time()
    for offset, action in events:
        while (left := started + offset - time.monotonic()) > 0:
            client.executor.spin_once(timeout_sec=min(0.002, left))
        action()
    ended = time.monotonic()
    bench.spin_for(WATCH_S)
    watched = time.monotonic()
    after = bench.fresh_status(watched + 0.1)  # counts include everything the node took
    outcome.rss_peak_mb = max(outcome.rss_peak_mb, sampler.stop() / 1024)
    outcome.hwm_mb = max(outcome.hwm_mb, tree_kb(pid, "VmHWM") / 1024)
    outcome.alive &= bench.node.poll() is None
    outcome.diagnostics_after &= after is not None
    client.node.destroy_publisher(attacker)
    if after is not None:
        for key in COUNTED:
            change = int(after.get(key, 0)) - int(before.get(key, 0))
            outcome.deltas[key] = outcome.deltas.get(key, 0) + change
    times = [started] + [t for t, _ in bench.diagnostics if started < t <= watched] + [watched]
    outcome.diagnostics_gap_s = max(outcome.diagnostics_gap_s, float(np.max(np.diff(times))))

    setpoints = list(client.setpoints)
    window = [s for s in setpoints if started <= s.received <= watched]
    if len(window) > 1:
        outcome.longest_gap_s = max(outcome.longest_gap_s,
                                    float(np.max(np.diff([s.received for s in window]))))
    sent = np.sort([s.sent for s in setpoints])
    first_tick = np.ceil((started_wall - phase) / period) * period + phase
    for tick in np.arange(first_tick, started_wall + (ended - started) + WATCH_S - period,
                          period):
        k = np.searchsorted(sent, tick - GRID_SLACK_S)
        outcome.lateness.append(max(0.0, (sent[k] if k < len(sent) else np.inf) - tick))

    ends = [z.published for z in zones[1:]] + [watched]
    for zone, end in zip(zones, ends):
        seen = [s for s in setpoints if zone.published < s.received <= end]
        first = next((i for i, s in enumerate(seen) if respects(zone.shape, s.point)), None)
        if first is None:
            zone.inside_before = len(seen)
            zone.inside_before_late = sum(s.sent > zone.published_wall for s in seen)
        else:
            zone.reaction = seen[first].received - zone.published
            zone.reaction_sent = seen[first].sent - zone.published_wall
            zone.inside_before = first
            zone.inside_before_late = sum(s.sent > zone.published_wall for s in seen[:first])
            zone.inside_after = sum(not respects(zone.shape, s.point) for s in seen[first:])
            answered = seen[first].received
            status = next((v for t, v in bench.diagnostics if answered < t <= end), None)
            if status is not None:
                zone.in_node_ms = float(status.get("zone_to_setpoint_ms", "nan"))
    outcome.zones += zones


# -- the report ---------------------------------------------------------------------------------

def ms_summary(values: list[float]) -> str:
    values = np.array(values, dtype=float)
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return "n/a"
    return f"{1000 * np.median(finite):.1f} / {1000 * np.max(finite):.1f}"


def table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  " + " | ".join(str(c).ljust(w) for c, w in zip(header, widths))]
    lines.append("  " + "-+-".join("-" * w for w in widths))
    lines += ["  " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) for r in rows]
    return "\n".join(lines)


def report(results: dict[tuple[str, str], Outcome], period: float) -> None:
    reaction_rows, health_rows = [], []
    for (condition, key), o in results.items():
        zones = o.zones
        in_node = [z.in_node_ms for z in zones if np.isfinite(z.in_node_ms)]
        reaction_rows.append([
            condition, key, str(len(zones)),
            ms_summary([z.reaction for z in zones]),
            ms_summary([z.reaction_sent for z in zones]),
            str(sum(not np.isfinite(z.reaction) for z in zones)),
            f"{sum(z.inside_before for z in zones)} "
            f"({sum(z.inside_before_late for z in zones)})",
            str(sum(z.inside_after for z in zones)),
            (f"{np.median(in_node):.1f} / {np.max(in_node):.1f} ({len(in_node)})"
             if in_node else "n/a")])
        late = np.array(o.lateness)
        late_text = (f"{1000 * np.percentile(late[np.isfinite(late)], 99):.1f} / "
                     f"{1000 * np.max(late):.1f} ({len(late)})" if len(late) else "n/a")
        d = o.deltas
        health_rows.append([
            condition, key,
            f"{o.rss_before_mb:.0f} / {o.rss_peak_mb:.0f} / {o.hwm_mb:.0f}"
            + ("" if o.hwm_reset else "*"),
            "yes" if o.alive else "NO", "yes" if o.diagnostics_after else "NO",
            f"{1000 * o.diagnostics_gap_s:.0f}",
            f"{d.get('zones_oversized', '?')} / {o.big_sent}", str(d.get("zone_messages", "?")),
            str(d.get("zones_refused", "?")), str(d.get("ticks_withheld", "?")),
            str(d.get("violations", "?")), str(d.get("ticks_missed", "?")), late_text,
            f"{1000 * o.longest_gap_s:.0f}"])
    print("\nOperator zones: published -> first setpoint that respects it (outside the zone "
          "grown by 15 px), ms median / max")
    print(table(reaction_rows, ["condition", "attack", "zones", "received", "sent by policy",
                                "unanswered", "inside before (sent after)", "inside after",
                                "node zone_to_setpoint_ms med / max (n)"]))
    processes = max(o.processes for o in results.values())
    print(f"\nThe node during the attack (RSS MB: the policy node's {processes} processes; "
          f"counts: change over the attack; tick lateness vs the {1000 * period:.0f} ms grid, "
          f"ms p99 / max (ticks))")
    print(table(health_rows, ["condition", "attack", "RSS before / peak / VmHWM", "alive",
                              "diag after", "diag gap ms", "oversized / sent", "zone_messages",
                              "refused", "withheld", "violations", "missed",
                              "tick late p99 / max",
                              "longest gap rcvd ms"]))
    if any(not o.hwm_reset for o in results.values()):
        print("  * VmHWM could not be reset: the peak since the node started")
    print("\nPer operator zone (received ms / setpoints inside before it):")
    for (condition, key), o in results.items():
        listed = ", ".join(
            ("unanswered" if not np.isfinite(z.reaction) else f"{1000 * z.reaction:.0f}")
            + f"/{z.inside_before}" for z in o.zones)
        print(f"  {condition} {key}: {listed}")
        for note in o.notes:
            print(f"    {note}")


def run_condition(args: argparse.Namespace, condition: str, payloads: dict[str, bytes],
                  base: Path, results: dict[tuple[str, str], Outcome]) -> None:
    loaded = condition == "loaded"
    label = f"loaded ({args.load} busy process(es))" if loaded else "idle"
    print(f"\n== {label} ==", flush=True)
    with background_load(args.load if loaded else 0):
        bench = Bench(args, base / condition)
        try:
            bench.start()
            first = bench.fresh_status(0.0, 10.0) or {}
            print("  node: " + ", ".join(f"{key} {first.get(key, '?')}" for key in (
                "clock_realtime", "executor_realtime")), flush=True)
            seed = FIRST_SEED
            for key in args.attacks:
                outcome = results.setdefault((condition, key), Outcome())
                for repeat in range(args.repeats):
                    if bench.stack.failed():  # the last attack killed it: a fresh stack
                        outcome.notes.append(f"restarted before repeat {repeat + 1}: "
                                             f"{bench.stack.failed()}")
                        bench.stop()
                        bench.start()
                    started = time.monotonic()
                    run_attack(bench, ATTACKS[key], payloads[key], seed, outcome)
                    seed += 1
                    print(f"  {key} ({ATTACKS[key].title}), repeat {repeat + 1}: "
                          f"{time.monotonic() - started:.0f} s", flush=True)
        finally:
            bench.stop()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.repeats < 1 or args.rate_hz <= 0:
        print("bench_hostile: --repeats and --rate-hz must be positive", file=sys.stderr)
        return 2
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    checkout = Path(__file__).resolve().parents[1]
    if checkout != SOURCE_ROOT:
        print(f"bench_hostile: this script is in {checkout}, but the package it runs is "
              f"{SOURCE_ROOT}'s; to measure this checkout: PYTHONPATH={checkout}",
              file=sys.stderr)
    base = Path(args.log_dir or tempfile.mkdtemp(prefix="bench_hostile_"))
    payloads = {key: zone_bytes(ATTACKER_ID, ATTACKS[key].vertices) for key in args.attacks}
    print(f"hostile zone messages: model {args.model}, {args.configuration}, realtime "
          f"{args.rate_hz:g} Hz; attacks {' '.join(args.attacks)}; logs in {base}")
    print("  big messages: " + ", ".join(f"{key} {len(p) / 1e6:.1f} MB"
                                         for key, p in payloads.items()))
    results: dict[tuple[str, str], Outcome] = {}
    started = time.monotonic()
    try:
        for condition in args.conditions:
            run_condition(args, condition, payloads, base, results)
    except KeyboardInterrupt:
        print("interrupted; node processes stopped", file=sys.stderr)
        return 130
    except RuntimeError as error:
        print(f"bench_hostile: {error}", file=sys.stderr)
        if results:
            report(results, 1.0 / args.rate_hz)
        return 1
    report(results, 1.0 / args.rate_hz)
    print(f"\n({time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
