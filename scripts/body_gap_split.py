"""Where the body-safe row loses score: the episodes split by what the point-safe row's disc did.

One batch, the same scenes for three DDIM 10 rows:
  - point-safe (`ddim10_r_g10_p`): no setpoint in a zone, the disc free to enter one;
  - point-safe on the zones grown by the pusher radius (the same with `inflate`), no filter;
  - body-safe (`ddim10_r_g10_p_safe`): the disc kept out too.
Each scenario's episodes are split into those where the point-safe row's disc entered a zone
(from outside one) and those where it stayed out on its own (episodes that start inside are in
neither). For each row and each part it prints s (mean best score) with a 95% bootstrap
interval, and in how many episodes the row's own disc entered a zone from outside. If the
body-safe row scores as high where the point-safe one keeps the disc out by itself, what it
loses is the score the point-safe row earns with its disc inside the zones.

  OMP_NUM_THREADS=2 .venv/bin/python scripts/body_gap_split.py --episodes 100
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
import torch

from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean
from constrained_diffusion_ros.evaluation.runner import evaluate_configurations
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT

SMALL_OBSTACLES = ["posts", "u_below", "triangle_top", "thin_wall"]
FIRST_SEED = 100000


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--scenarios", nargs="+", default=SMALL_OBSTACLES,
                        help="static scenarios of config/scenarios.yaml")
    parser.add_argument("--episodes", type=int, default=100,
                        help=f"scenes per cell (seeds {FIRST_SEED} on)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    return parser


def entered(pusher: np.ndarray, scenario) -> tuple[np.ndarray, np.ndarray]:
    """(episodes,) whether the disc overlapped a zone after the start, and at the start."""
    area = scenario.zones_at(0)
    clearance = area.signed_distance(torch.from_numpy(pusher)).numpy()
    overlap = clearance < PUSHT_ROBOT.pusher_radius
    return overlap[:, 1:].any(axis=1), overlap[:, 0]


def cell(scores: np.ndarray) -> str:
    if len(scores) == 0:
        return "-"
    low, high = bootstrap_mean(scores)
    return f"{scores.mean():.3f} [{low:.3f}, {high:.3f}]"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    scenarios = load_scenarios(config_dir() / "scenarios.yaml")
    unknown = [name for name in args.scenarios if name not in scenarios]
    moving = [name for name in args.scenarios if name in scenarios and scenarios[name].moving]
    if unknown or moving:
        print(f"error: {'unknown' if unknown else 'moving'} scenarios: "
              f"{', '.join(unknown or moving)} (static ones of config/scenarios.yaml only)",
              file=sys.stderr)
        return 2
    configs = load_configurations(config_dir() / "configurations.yaml")
    point = configs["ddim10_r_g10_p"]
    rows = {"point-safe": point,
            "point-safe, zones grown": dataclasses.replace(point, name="ddim10_r_g10_p_grown",
                                                           inflate=True),
            "body-safe": configs["ddim10_r_g10_p_safe"]}
    chosen = [scenarios[name] for name in args.scenarios]
    seeds = list(range(FIRST_SEED, FIRST_SEED + args.episodes))
    _, log, first = evaluate_configurations(load_policy(args.model), list(rows.values()),
                                            [chosen] * len(rows), seeds)
    print(f"\n{args.episodes} scenes per cell (seeds {seeds[0]}-{seeds[-1]}), DDIM 10; s with "
          f"95% intervals: all episodes / the point-safe disc entered a zone / it stayed out\n")
    print("| scenario | row | all | point-safe disc entered | stayed out | the row's own disc "
          "entered |")
    print("| --- | --- | --- | --- | --- | --- |")
    grown_split = []
    for scenario in chosen:
        block = {config.name: slice(first[(scenario.name, config.name)],
                                    first[(scenario.name, config.name)] + len(seeds))
                 for config in rows.values()}
        went_in, started_in = entered(log.pusher[block[point.name]], scenario)
        parts = (went_in & ~started_in, ~went_in & ~started_in)
        own_in = {}
        for label, config in rows.items():
            best = log.best_score[block[config.name]]
            own, own_start = entered(log.pusher[block[config.name]], scenario)
            own_in[label] = own & ~own_start
            print(f"| {scenario.name} ({parts[0].sum()} / {parts[1].sum()}) | {label} | "
                  f"{cell(best)} | {cell(best[parts[0]])} | {cell(best[parts[1]])} | "
                  f"{own_in[label].sum()} |")
        grown = own_in["point-safe, zones grown"]
        for split, where in (("also entered", parts[0] & grown), ("stayed out", parts[0] & ~grown)):
            scores = [cell(log.best_score[block[config.name]][where]) for config in rows.values()]
            grown_split.append(f"| {scenario.name} | {split} ({where.sum()}) | "
                               + " | ".join(scores) + " |")
    print("\nThe episodes where the point-safe disc entered a zone, split by whether the disc of "
          "the point-safe row on grown zones did too:\n")
    print("| scenario | grown row's disc | " + " | ".join(rows) + " |")
    print("| --- | --- |" + " --- |" * len(rows))
    print("\n".join(grown_split))
    return 0


if __name__ == "__main__":
    sys.exit(main())
