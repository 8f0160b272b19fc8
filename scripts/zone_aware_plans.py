"""What a zone-aware policy learned: how often its raw plan (no hooks, no filter) runs the
pusher's disc into the zones, given the zones in its condition and not given them.

States are the human demonstrations' (in the policy's own distribution, where the route runs
anywhere), each scenario's zones laid over them; states whose disc already touches a zone are
left out. For every state one plan with each condition from the same noise (DDIM 10); a plan
enters the zones if any waypoint of its executed part lies in the zones grown by the pusher's
radius. Prints, per scenario: the states kept, the share of plans that enter without the
condition and with it (`--guidance`: its zone_guidance), and among the states whose blind plan
enters, the share the condition keeps out. A policy that does not see zones prints the same
figure twice. Asserts nothing.

  OMP_NUM_THREADS=2 .venv/bin/python scripts/zone_aware_plans.py --model models/pusht_lowdim_zones
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.policy_config import PolicyConfig
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.sampling.sampler import DenoisingSampler
from constrained_diffusion_ros.training.dataset import (
    WindowSampler,
    load_demonstrations,
)

SCENARIOS = ("left_0.1", "left_0.5", "center_0.1", "center_0.2", "posts", "u_below",
             "triangle_top", "thin_wall", "u_wide", "c_arc", "zigzag_top", "long_diagonal",
             "e_comb")


def checkpoint_policy(directory: Path) -> DiffusionPolicy:
    """A checkpoint's EMA weights as a policy (what training would save at that step)."""
    from safetensors.torch import load_file

    meta = json.loads((directory / "state.json").read_text())
    policy = DiffusionPolicy(PolicyConfig.from_dict(meta["policy"]))
    tensors = load_file(str(directory / "state.safetensors"))
    policy.unet.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("ema.")})
    print(f"checkpoint {directory} at step {meta['step']}")
    return policy.eval().requires_grad_(False)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=str(default_model_dir()))
    parser.add_argument("--checkpoint", default=None, metavar="DIR",
                        help="a training checkpoint (train_policy's OUTPUT/checkpoint) instead "
                             "of --model: its EMA weights, as training goes")
    parser.add_argument("--dataset", default="../shared/datasets/pusht_cchi_v7_replay.zarr")
    parser.add_argument("--states", type=int, default=1000, help="demonstration states drawn")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--guidance", type=float, default=1.0,
                        help="zone_guidance of the plans that see the zones")
    args = parser.parse_args()
    policy = load_policy(args.model) if args.checkpoint is None else checkpoint_policy(
        Path(args.checkpoint))
    config = policy.config
    windows = WindowSampler(load_demonstrations(args.dataset), config.horizon,
                            config.n_obs_steps, config.n_action_steps)
    generator = torch.Generator().manual_seed(args.seed)
    chosen = torch.randperm(len(windows), generator=generator)[:args.states]
    observations, _ = windows.batch(chosen)
    scenarios = load_scenarios(config_dir() / "scenarios.yaml")
    sampler = DenoisingSampler(policy, "ddim", 10, "trailing", zone_guidance=args.guidance)
    executed = slice(config.first_executed, config.first_executed + config.n_action_steps)
    radius = PUSHT_ROBOT.pusher_radius
    print(f"{args.checkpoint or args.model}: sees zones {config.sees_zones}; {args.states} "
          f"demonstration states, DDIM 10, seed {args.seed}, zone guidance {args.guidance}")
    print(f"{'scenario':<16}{'states':>8}{'blind enter':>13}{'seeing enter':>14}"
          f"{'kept out':>10}")
    for name in args.scenarios:
        grown = scenarios[name].zones_at(0).inflate(radius)
        pusher = observations[:, -1, -2:].double()
        free = ~grown.contains(pusher)
        obs = observations[free]
        noise_seed = args.seed + 1
        plans = {seeing: sampler.sample(obs, torch.Generator().manual_seed(noise_seed), (),
                                        scenarios[name].zones_at(0) if seeing else None)
                 for seeing in (False, True)}
        enters = {k: grown.contains(v[:, executed].double()).any(1) for k, v in plans.items()}
        blind = enters[False]
        kept = (blind & ~enters[True]).sum() / max(1, int(blind.sum()))
        print(f"{name:<16}{len(obs):>8}{float(blind.float().mean()):>13.3f}"
              f"{float(enters[True].float().mean()):>14.3f}{float(kept):>10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
