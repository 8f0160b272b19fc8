"""Where DDIM's score goes: the unconstrained policy under sampler variants, against DDPM.

Runs the shipped policy without zones on `--episodes` seeded scenes (from seed 100000, 200
steps, all episodes in one batch) with DDPM over all training steps (the reference) and with
DDIM variants: number of steps, timestep spacing (diffusers' leading / trailing / linspace),
eta. Prints per variant the network calls per chunk, s (mean best coverage score) with its 95%
bootstrap interval, and the paired difference to DDPM on the same scenes with its interval.
Asserts nothing.

  scripts/study_ddim.py --episodes 200
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from constrained_diffusion_ros.cli import positive_int
from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean
from constrained_diffusion_ros.evaluation.rollout import rollout
from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT

REFERENCE = ConstraintConfig("ddpm100")
VARIANTS = {  # name: (steps, spacing, eta)
    "ddim10 leading": (10, "leading", 0.0),
    "ddim10 trailing": (10, "trailing", 0.0),
    "ddim10 linspace": (10, "linspace", 0.0),
    "ddim10 trailing eta 1": (10, "trailing", 1.0),
    "ddim16 leading": (16, "leading", 0.0),
    "ddim16 trailing": (16, "trailing", 0.0),
    "ddim8 trailing": (8, "trailing", 0.0),
    "ddim5 trailing": (5, "trailing", 0.0),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()))
    parser.add_argument("--episodes", type=positive_int, default=200)
    parser.add_argument("--first-seed", type=int, default=100000)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS),
                        choices=list(VARIANTS), metavar="VARIANT")
    parser.add_argument("--threads", type=positive_int, default=2, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = load_policy(args.model)
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    configs = [REFERENCE] + [
        ConstraintConfig(name, sampler="ddim", denoising_steps=steps, timestep_spacing=spacing,
                         eta=eta)
        for name, (steps, spacing, eta) in VARIANTS.items() if name in args.variants]
    print(f"unconstrained, {len(seeds)} scenes from seed {seeds[0]}, 200 steps, "
          f"{args.threads} torch threads")
    print(f"{'sampler':24} {'calls':>5} {'s [95% CI]':>22} {'s - DDPM [95% CI]':>26} "
          f"{'wall s':>7}")
    reference = None
    for config in configs:
        started = time.monotonic()
        planner = ConstrainedPlanner(policy, config, PUSHT_ROBOT)
        log = rollout(planner, seeds, 200, None, torch.Generator().manual_seed(0),
                      progress=True, description=config.name)
        best = log.best_score
        reference = best if reference is None else reference
        low, high = bootstrap_mean(best)
        d_low, d_high = bootstrap_mean(best - reference)
        calls = config.denoising_steps or policy.config.num_train_timesteps
        print(f"{config.name:24} {calls:5d} {best.mean():7.3f} [{low:.3f}, {high:.3f}] "
              f"{np.mean(best - reference):+8.3f} [{d_low:+.3f}, {d_high:+.3f}] "
              f"{time.monotonic() - started:7.0f}", flush=True)


if __name__ == "__main__":
    main()
