"""Benchmark the ROS-free PushT simulator: simulated 10 Hz control steps per second.

Reports a single PushTSim and PushTBatch at several batch sizes, so planners can budget
rollouts. Actions chase each block so that contacts (the expensive case) happen.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sim_bridge import PushTBatch, PushTSim


def _actions(rs: np.random.RandomState, states: np.ndarray) -> np.ndarray:
    """Targets near each block, clipped to the workspace."""
    return np.clip(states[:, 2:4] + rs.uniform(-60.0, 60.0, (len(states), 2)), 10.0, 500.0)


def bench_single(steps: int, seed: int) -> float:
    sim = PushTSim()
    state = sim.reset(seed)
    rs = np.random.RandomState(seed)
    start = time.perf_counter()
    for _ in range(steps):
        state = sim.step(_actions(rs, state[None])[0])
    return steps / (time.perf_counter() - start)


def bench_batch(n: int, steps: int, seed: int) -> tuple[float, float]:
    """Returns (scene-steps per second, batch steps per second), scoring included."""
    batch = PushTBatch(n)
    states = batch.reset(list(range(seed, seed + n)))
    rs = np.random.RandomState(seed)
    start = time.perf_counter()
    for _ in range(steps):
        states = batch.step(_actions(rs, states))
        batch.coverage()
    elapsed = time.perf_counter() - start
    return n * steps / elapsed, steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=500, help="control steps per run (single)")
    parser.add_argument(
        "--batch-steps", type=int, default=40, help="control steps per run (batched)"
    )
    parser.add_argument(
        "--batch-sizes", type=int, nargs="+", default=[25, 100], help="batch sizes to time"
    )
    parser.add_argument("--seed", type=int, default=0, help="first scene seed")
    args = parser.parse_args()

    rate = bench_single(args.steps, args.seed)
    print(f"single PushTSim: {rate:,.0f} control steps/s ({rate / 10:.1f}x real time at 10 Hz)")
    for n in args.batch_sizes:
        scene_rate, batch_rate = bench_batch(n, args.batch_steps, args.seed)
        print(
            f"PushTBatch({n}): {scene_rate:,.0f} scene-steps/s, {batch_rate:,.1f} batch steps/s "
            "(with coverage)"
        )


if __name__ == "__main__":
    main()
