"""Unconstrained closed-loop benchmark of a policy: `benchmark_policy --help`.

Runs seeded PushT scenes (the reference evaluates from seed 100000 upward) for a fixed number of
action steps, all episodes batched, and prints mean best score, mean final score, success rate
and wall time.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from constrained_diffusion_ros.cli import (
    ArgumentParser,
    add_compute_arguments,
    load_policy_for,
    positive_int,
    run_command,
)
from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.policy.schedulers import SPACINGS


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser("benchmark_policy", __doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--first-seed", type=int, default=100000)
    parser.add_argument("--episodes", type=positive_int, default=50)
    parser.add_argument("--steps", type=positive_int, default=200,
                        help="action steps per episode")
    parser.add_argument("--sampler", choices=["ddpm", "ddim"], default="ddpm")
    parser.add_argument("--denoising-steps", type=positive_int, default=None,
                        help="inference steps (default: all 100 for DDPM)")
    parser.add_argument("--timestep-spacing", choices=SPACINGS, default="leading",
                        help="which training timesteps a shorter schedule visits")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampling noise")
    add_compute_arguments(parser)
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def run(args: argparse.Namespace) -> int:
    import torch

    from constrained_diffusion_ros.evaluation.rollout import rollout
    from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT

    policy = load_policy_for(args)
    unconstrained = ConstraintConfig("none", sampler=args.sampler,
                                     denoising_steps=args.denoising_steps,
                                     timestep_spacing=args.timestep_spacing)
    planner = ConstrainedPlanner(policy, unconstrained, PUSHT_ROBOT)
    generator = torch.Generator().manual_seed(args.seed)
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    started = time.monotonic()
    log = rollout(planner, seeds, args.steps, generator=generator, progress=True,
                  description="benchmark")
    wall = time.monotonic() - started
    figures = {
        "episodes": len(seeds), "seeds": f"{seeds[0]}..{seeds[-1]}", "action_steps": args.steps,
        "sampler": f"{args.sampler}-{planner.sampler.num_inference_steps}",
        "timestep_spacing": args.timestep_spacing, "device": str(policy.device),
        "mean_best_score": float(log.best_score.mean()),
        "mean_final_score": float(log.final_score.mean()),
        "success_rate": float(log.success.mean()), "wall_time_s": round(wall, 1),
    }
    for key, value in figures.items():
        print(f"{key:>17}: {value:.3f}" if isinstance(value, float) else f"{key:>17}: {value}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(figures, handle, indent=2)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command(run, build_parser().parse_args(argv), "benchmark_policy")


if __name__ == "__main__":
    sys.exit(main())
