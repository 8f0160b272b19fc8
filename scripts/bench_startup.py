"""How long the policy node takes to come up in real-time mode: from starting its process to the
first setpoint a client receives (the pusher held where it is) and to the first plan (the robot
starts its task), with the node's own account of where the time went (its
start-up log line: imports, weights, the runtime's export and check, the planner and its
planning process). The simulator runs already, so the first setpoint comes as soon as the policy
can answer. Idle, then beside busy processes that the script starts and stops itself. Prints
figures; asserts nothing.

With --help-times: how long each console script takes to answer `--help` instead (issue 45:
at once, its heavy imports come after the arguments are read), the median over --runs.

Run: OMP_NUM_THREADS=1 python scripts/bench_startup.py [--runs 3] [--help-times]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import distribution
from pathlib import Path

from bench_realtime import add_condition_arguments, background_load
from live_client import Client

from constrained_diffusion_ros.evaluation.launcher import Stack
from constrained_diffusion_ros.paths import default_model_dir


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--configuration", default="ddim10_r_g10_p_safe")
    parser.add_argument("--runs", type=int, default=3, help="start-ups per condition")
    parser.add_argument("--timeout", type=float, default=120.0, help="s to wait for a setpoint")
    parser.add_argument("--help-times", action="store_true",
                        help="time each console script's --help instead of the node's start-up")
    add_condition_arguments(parser)
    return parser


def one_start(args: argparse.Namespace, log_dir: Path) -> tuple[float, float, str]:
    """Seconds from starting the policy node to the first setpoint and to the first plan; its
    start-up log line."""
    stack = Stack("bench_startup", log_dir)
    client = Client(stack)
    try:
        stack.start("sim_node", mode="realtime", autostart=True)
        client.spin_until(lambda: len(client.pushers) > 0, args.timeout, "the simulator")
        started = time.monotonic()
        log = stack.start("policy_node", model=args.model, mode="realtime",
                          configuration=args.configuration)
        client.spin_until(lambda: len(client.setpoints) > 0, args.timeout, "a setpoint")
        first = client.setpoints[0].received - started
        client.spin_until(lambda: len(client.plan_times) > 0, args.timeout, "a plan")
        plan = client.plan_times[0] - started
        line = next((m.group(1) for m in re.finditer(r"start-up: (.*)", log.read_text())), "?")
        return first, plan, line
    finally:
        client.close()
        stack.close()


def help_times(args: argparse.Namespace) -> int:
    """Each installed console script's `--help`, timed from its start to its exit: the median
    and the slowest of --runs, per condition."""
    scripts = sorted(e.name for e in distribution("constrained_diffusion_ros").entry_points
                     if e.group == "console_scripts")
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    for condition in args.conditions:
        print(f"\n== {condition}: --help, {args.runs} runs each ==", flush=True)
        with background_load(args.load if condition == "loaded" else 0):
            for name in scripts:
                seconds = []
                for _ in range(args.runs):
                    started = time.perf_counter()
                    subprocess.run([str(Path(sys.executable).parent / name), "--help"],
                                   stdout=subprocess.DEVNULL, env=environment, check=True)
                    seconds.append(time.perf_counter() - started)
                print(f"  {name:>16}: median {statistics.median(seconds):.2f} s, max "
                      f"{max(seconds):.2f} s", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.help_times:
        return help_times(args)
    base = Path(tempfile.mkdtemp(prefix="bench_startup_"))
    print(f"policy node start-up, realtime, {args.configuration}; logs in {base}")
    for condition in args.conditions:
        loaded = condition == "loaded"
        print(f"\n== {condition} ==", flush=True)
        with background_load(args.load if loaded else 0):
            seconds, plans = [], []
            for run in range(args.runs):
                log_dir = base / f"{condition}_{run}"
                log_dir.mkdir(parents=True)
                first, plan, line = one_start(args, log_dir)
                seconds.append(first)
                plans.append(plan)
                print(f"  run {run + 1}: first setpoint {first:.1f} s, first plan {plan:.1f} s "
                      f"after the process started; the node: {line}", flush=True)
        print(f"  first setpoint: median {statistics.median(seconds):.1f} s, max "
              f"{max(seconds):.1f} s; first plan: median {statistics.median(plans):.1f} s, max "
              f"{max(plans):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
