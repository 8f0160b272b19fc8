"""How late the control clock's ticks come with one thread and with two pinned to different CPUs
(`ControlClock(threads=...)`), in alternated runs, with the hypervisor's share of the CPU (steal)
during each: on a virtual machine a thread whose timer is on a CPU the hypervisor has taken away
wakes late whatever its priority, and two threads wait for the same deadlines so that a tick is
late only when both CPUs are taken at once. Idle, then beside busy processes that the script
starts and stops itself. The tick sends nothing, so the figures are the clock's own. Prints a
table; asserts nothing.

Run: python scripts/bench_clock.py [--rate-hz 100] [--seconds 20] [--pairs 4]
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import threading

import numpy as np
from bench_realtime import add_condition_arguments, background_load, cpu_times

from constrained_diffusion_ros.runtime.clock import ControlClock


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--rate-hz", type=float, default=100.0, help="tick rate")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of one run")
    parser.add_argument("--pairs", type=int, default=4,
                        help="runs of each thread count per condition, alternated")
    add_condition_arguments(parser)
    return parser


def one_run(threads: int, args: argparse.Namespace) -> tuple[np.ndarray, float, int]:
    """Lateness of every tick (ms), steal during the run (%), ticks missed."""
    ticks, sent = int(args.seconds * args.rate_hz), itertools.count(1)
    done = threading.Event()
    before = cpu_times()
    clock = ControlClock(args.rate_hz, lambda: done.set() if next(sent) >= ticks else None,
                         threads=threads, window=ticks)
    try:
        done.wait(2 * args.seconds + 5)
    finally:
        clock.shutdown()
    steal, total = cpu_times() - before
    return 1000 * np.array(clock.lateness), 100 * steal / max(total, 1), clock.missed


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    print(f"control clock at {args.rate_hz:g} Hz, runs of {args.seconds:g} s, "
          f"{os.cpu_count()} CPUs")
    print("| condition | threads | steal | late p50 | late p99 | late max | missed |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for condition in args.conditions:
        with background_load(args.load if condition == "loaded" else 0):
            for _ in range(args.pairs):
                for threads in (1, 2):
                    late, steal, missed = one_run(threads, args)
                    print(f"| {condition} | {threads} | {steal:.2f}% | {np.median(late):.2f} ms "
                          f"| {np.percentile(late, 99):.2f} ms | {late.max():.2f} ms "
                          f"| {missed} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
