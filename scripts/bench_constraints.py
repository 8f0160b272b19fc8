"""Benchmark the constraint hooks: overhead per chunk against the plain sampler, the
from-scratch baseline's compute against the hooks' at equal violations, and the shield's cost
per executed step.

Open loop, on real observations: windows drawn from the demonstrations, every chunk planned
with a scenario's zones; "violations" = executed waypoints (the 8 that run) inside the zone,
per chunk, with a 95% bootstrap interval over the observations (each observation's chunks
averaged first: its repeats share it, so they are not independent). Prints a table; asserts
nothing.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from constrained_diffusion_ros.evaluation.intervals import bootstrap_mean
from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.paths import default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import ConstraintConfig
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.training.dataset import WindowSampler, load_demonstrations

DEFAULT_DATASET = Path(__file__).resolve().parents[1].parent / "shared/datasets/" \
    "pusht_cchi_v7_replay.zarr"


def measure(planner: ConstrainedPlanner, obs: torch.Tensor, area, repeats: int
            ) -> tuple[float, torch.Tensor]:
    """ms per batched call, and the violating executed waypoints (B,) per observation, averaged
    over the repeats."""
    generator = torch.Generator().manual_seed(0)
    planner.plan(obs, area, generator=generator)  # warm-up
    started = time.perf_counter()
    violations = []
    for _ in range(repeats):
        chunk = planner.plan(obs, area, generator=generator)
        first, n = planner.policy.config.first_executed, planner.policy.config.n_action_steps
        violations.append(area.contains(chunk[:, first: first + n]).sum(dim=1).float())
    ms = 1000 * (time.perf_counter() - started) / repeats
    return ms, torch.stack(violations).mean(dim=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()))
    parser.add_argument("--dataset", default=str(DEFAULT_DATASET))
    parser.add_argument("--scenario", default="center_0.2")
    parser.add_argument("--batch", type=int, default=100,
                        help="observations (distinct windows) per batched call")
    parser.add_argument("--repeats", type=int, default=2, help="calls per row")
    args = parser.parse_args()

    policy = load_policy(args.model)
    demos = load_demonstrations(args.dataset)
    c = policy.config
    windows = WindowSampler(demos, c.horizon, c.n_obs_steps, c.n_action_steps)
    ids = torch.randperm(len(windows), generator=torch.Generator().manual_seed(0))[: args.batch]
    obs, actions = windows.batch(ids)
    area = load_scenarios()[args.scenario].zones_at(0)

    rows = [("plain DDPM 100", ConstraintConfig("none"))]
    rows += [(f"DDPM 100 {name}", ConstraintConfig(name, **kw)) for name, kw in (
        ("resampling", {"resample": True}), ("gradient 10", {"push": 10}),
        ("R + G10", {"resample": True, "push": 10}),
        ("R + G10 + P + inflation + path", {"resample": True, "push": 10, "project": True,
                                            "inflate": True, "path_repair": True}))]
    rows += [("plain DDIM 10", ConstraintConfig("d", sampler="ddim", denoising_steps=10)),
             ("DDIM 10 R + G10", ConstraintConfig("d", sampler="ddim", denoising_steps=10,
                                                 resample=True, push=10))]
    rows += [(f"DDIM 10 from scratch N={n}", ConstraintConfig(
        "s", sampler="ddim", denoising_steps=10, from_scratch=n)) for n in (2, 4, 8, 16, 32)]
    print(f"scenario {args.scenario}, {args.batch} observations per call, {args.repeats} calls "
          f"per row ({args.batch * args.repeats} chunks), {torch.get_num_threads()} threads")
    print(f"{'method':<40} {'ms/call':>9} {'ratio':>7} {'violations/chunk [95% interval]':>32}")
    base = {}
    for label, config in rows:
        planner = ConstrainedPlanner(policy, config, PUSHT_ROBOT)
        ms, violations = measure(planner, obs, area, args.repeats)
        reference = base.setdefault(config.sampler, ms)
        low, high = bootstrap_mean(violations.numpy())
        print(f"{label:<40} {ms:9.1f} {ms / reference:7.2f} "
              f"{violations.mean().item():17.3f} [{low:.3f}, {high:.3f}]")

    # The shield runs once per executed step, outside the denoising loop: its cost per step for
    # the same pushers, each commanded to its demonstrated next action.
    planner = ConstrainedPlanner(policy, ConstraintConfig("shield", inflate=True, shield=True),
                                 PUSHT_ROBOT)
    latest = obs[:, -1].numpy()
    setpoints = actions[:, c.first_executed].double().numpy()
    started = time.perf_counter()
    for step in range(args.repeats * 10):
        planner.guard(area, latest, setpoints, step)
    ms = 1000 * (time.perf_counter() - started) / (args.repeats * 10)
    print(f"{'shield, per executed step':<40} {ms:9.1f} {'':>7} "
          f"{planner.shield.corrected / (args.repeats * 10):17.3f} corrected setpoints/step")


if __name__ == "__main__":
    main()
