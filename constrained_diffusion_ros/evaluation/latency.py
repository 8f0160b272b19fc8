"""What planning latency costs, measured deterministically: `latency --help`.

The batched evaluation with an inference delay of d control steps (the chunk asked for at step
t, from t's observation, is ready at t + d), run by the policy node's own loop (`ChunkLoop`)
with a simulated worker, and three handovers: sync (the robot waits for the plan, holding its
setpoint), async (the chunk in force goes on; the new one skips the steps that passed) and
async_prefix (async with the committed waypoints inpainted into the new chunk). Reports s, r,
r_body and the jump at chunk handovers (the distance between consecutive setpoints where a new
chunk takes over, against the same within a chunk) and writes docs/latency.md and latency.json.
With `--every-tick`, also every_tick: a plan asked at every observation that finds none on its
way (async_prefix, the waypoints due before it arrives held fixed). Each run's seeds go in units
of --unit, here or with --ray as Ray tasks, as in `evaluate`.
"""

from __future__ import annotations

import argparse
import json
import sys
from contextlib import closing
from pathlib import Path

import numpy as np

from constrained_diffusion_ros.cli import ArgumentParser, positive_int, run_command
from constrained_diffusion_ros.evaluation import distributed
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations

# Seeds of evaluation.runner.DEFAULT_SEEDS, written out: runner imports torch, and --help shows
# the number before any of it (test/unit/test_help_imports.py keeps the two equal).
DEFAULT_EPISODES = 25


def handover_jumps(commanded: np.ndarray, executed_chunk: np.ndarray) -> tuple[float, float]:
    """Mean distance between consecutive setpoints (E, T, 2) where a new chunk takes over from
    another or from a held setpoint (the first chunk of an episode excluded), and within one;
    NaN where there is none (a plan every tick: no two steps of one chunk)."""
    step = np.linalg.norm(np.diff(commanded, axis=1), axis=-1)  # (E, T - 1)
    before, after = executed_chunk[:, :-1], executed_chunk[:, 1:]
    first = np.where(executed_chunk >= 0, executed_chunk, np.iinfo(np.int64).max).min(axis=1)
    handover = (after != before) & (after >= 0) & (after != first[:, None])
    within = (after == before) & (after >= 0)
    def mean(mask: np.ndarray) -> float:
        return float(step[mask].mean()) if mask.any() else float("nan")
    return mean(handover), mean(within)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser("latency", __doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--configs", nargs="+", default=["ddim10_r_g10_p_safe", "r_g10_p_safe"],
                        help="configuration names from config/configurations.yaml")
    parser.add_argument("--scenarios", nargs="+", default=["center_0.2", "left_0.1"],
                        help="scenario names from config/scenarios.yaml")
    parser.add_argument("--delays", nargs="+", type=int, default=[0, 1, 2, 4],
                        help="inference delays, control steps")
    parser.add_argument("--every-tick", nargs="*", default=["ddim10_r_g10_p_safe"],
                        metavar="CONFIG",
                        help="configurations also run with a plan asked at every tick "
                             "(every_tick: async_prefix from the newest observation; d=0 and "
                             "1 plan at every step, so a DDPM configuration takes 8 times as "
                             "long)"),
    parser.add_argument("--episodes", type=positive_int, default=DEFAULT_EPISODES,
                        help="seeds from 100000 on")
    parser.add_argument("--steps", type=positive_int, default=200,
                        help="action steps per episode")
    parser.add_argument("--output", default="docs", help="where latency.md and .json go")
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads")
    distributed.add_ray_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    import torch

    from constrained_diffusion_ros.evaluation.runner import DEFAULT_SEEDS
    from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
    from constrained_diffusion_ros.planning.chunk_loop import EVERY_TICK, HANDOVERS
    from constrained_diffusion_ros.policy.weights import load_policy

    if min(args.delays) < 0:
        raise ValueError("--delays must be >= 0")
    if args.ray:  # arguments that do not go together are said before any work
        distributed.cluster_address(args)
    torch.set_num_threads(args.threads)
    directory = config_dir()
    known_scenarios = load_scenarios(directory / "scenarios.yaml")
    known_configs = load_configurations(directory / "configurations.yaml")
    unknown = [n for n in args.scenarios if n not in known_scenarios] + \
        [n for n in args.configs if n not in known_configs]
    if unknown:
        raise ValueError(f"unknown scenarios or configurations: {unknown}")
    scenarios = [known_scenarios[n] for n in args.scenarios]
    policy = load_policy(args.model)
    seeds = list(range(DEFAULT_SEEDS[0], DEFAULT_SEEDS[0] + args.episodes))
    unknown = [n for n in args.every_tick if n not in args.configs]
    if unknown:
        raise ValueError(f"--every-tick names configurations not in --configs: {unknown}")
    runs = [(c, d, h) for c in args.configs for d in args.delays
            for h in (*(HANDOVERS if d > 0 else HANDOVERS[:1]),
                      *((EVERY_TICK,) if c in args.every_tick else ()))]
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    kept = kept_rows(output / "latency.json", args.configs)
    groups = [distributed.Group([known_configs[name]], [scenarios], delay, handover)
              for name, delay, handover in runs]
    done: dict[int, list[dict]] = {}  # run index -> its rows, written in the runs' order

    def collected() -> list[dict]:
        return kept + [row for i in sorted(done) for row in done[i]]

    with closing(distributed.group_results(policy, groups, seeds, args.steps, args)) as results:
        for index, (cells, log, first_rows) in results:
            name, delay, handover = runs[index]
            by_scenario = {cell.scenario: cell for cell in cells}
            done[index] = []
            for scenario in scenarios:
                start = first_rows[(scenario.name, name)]
                block = np.arange(start, start + len(seeds))
                cell = by_scenario[scenario.name]
                jump, within = handover_jumps(log.commanded[block], log.executed_chunk[block])
                done[index].append({
                    "configuration": name, "scenario": scenario.name, "delay": delay,
                    "handover": handover if delay or handover == EVERY_TICK else "none",
                    "s": cell.s, "r": cell.r, "r_body": cell.r_body,
                    "jump_at_handover_px": jump, "step_within_chunk_px": within,
                    "episodes": len(seeds)})
            rows = collected()
            (output / "latency.json").write_text(json.dumps(rows, indent=1) + "\n")  # as it goes
            (output / "latency.md").write_text(markdown(rows, args))
    print(markdown(collected(), args))
    return 0


def kept_rows(path: Path, configs: list[str]) -> list[dict]:
    """The rows of other configurations already in `path`: a run for one configuration adds
    its rows to the report instead of replacing the others'."""
    if not path.exists():
        return []
    try:
        rows = json.loads(path.read_text())
    except ValueError as error:
        raise ValueError(f"{path} is not a latency report ({error}); move it away") from None
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ValueError(f"{path} is not a latency report; move it away")
    return [row for row in rows if row.get("configuration") not in configs]


def markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [
        "# What planning latency costs",
        "",
        f"Written by `latency` ({args.episodes} seeded episodes per row, {args.steps} steps). "
        "A chunk asked for at step t is ready at t + d. sync: the robot holds its setpoint "
        "until the plan is in. async: the chunk in force goes on and the new one skips the "
        "steps that passed. async_prefix: async with the committed waypoints inpainted into "
        "the new chunk (4 soft ones after them). every_tick: async_prefix with a plan asked "
        "at every step that has none on its way (a fresh plan every step at d = 0 and 1). "
        "Jump: mean distance between consecutive setpoints where a new chunk takes over; "
        "step: the same within a chunk (px). r counts setpoints inside a zone, r_body steps "
        "with the pusher's disc overlapping one. The chunk loop the policy node runs live "
        "(planning/chunk_loop.py) runs it, with a simulated worker whose plans arrive after "
        "d steps; live, they arrive when the planning process is done.",
        "",
        "| configuration | scenario | d | handover | s | r | r_body | jump px | step px |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['configuration']} | {r['scenario']} | {r['delay']} | "
                     f"{r['handover']} | {r['s']:.3f} | {r['r']:.2f} | {r['r_body']:.2f} | "
                     f"{r['jump_at_handover_px']:.1f} | {r['step_within_chunk_px']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return run_command(run, build_parser().parse_args(argv), "latency")


if __name__ == "__main__":
    sys.exit(main())
