"""Trains the PushT diffusion policy on the human demonstrations: `train_policy --help`.

Resumable (a checkpoint every `--checkpoint-every` steps holds the weights, their EMA, the
optimiser's moments and the random state, all as safetensors + JSON), reproducible from
`--seed`, and it writes the shipped artefact: EMA weights, config with normaliser stats, and
the loss curve as PNG and JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from constrained_diffusion_ros.cli import (
    ArgumentParser,
    add_compute_arguments,
    positive_int,
    run_command,
    use_compute_arguments,
)
from msg_schemas.text import one_line

if TYPE_CHECKING:  # torch, the network and the dataset are imported once the arguments are read
    import torch

    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy

CHECKPOINT_DIR = "checkpoint"
ZONE_GRID = 32  # a zone-aware policy's raster: 16 px cells over PushT's 512 px
SHAPES = 4096  # zone shapes drawn for training
ROUTES_PER_WINDOW = 3  # plans of the --init-from policy per window, where zones are anchored


class EmaWeights:
    """EMA of the weights with the reference's warm-up: decay = 1 - (1 + step)^-0.75, capped.

    Kept as a plain tensor dict (not diffusers' EMAModel) so a checkpoint is one safetensors file.
    """

    def __init__(self, model: torch.nn.Module, power: float = 0.75, max_decay: float = 0.9999):
        self.power, self.max_decay = power, max_decay
        self.shadow = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def update(self, model: torch.nn.Module, step: int) -> None:
        import torch

        with torch.no_grad():
            decay = min(self.max_decay, 1.0 - (1.0 + step) ** -self.power)
            current = model.state_dict()
            torch._foreach_lerp_(list(self.shadow.values()),
                                 [current[k] for k in self.shadow], 1.0 - decay)


def cosine_with_warmup(step: int, warmup: int, total: int) -> float:
    if step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(1, total - warmup)
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def save_checkpoint(directory: Path, step: int, policy: DiffusionPolicy, ema: EmaWeights,
                    optimizer: torch.optim.Optimizer, generator: torch.Generator,
                    losses: list[float]) -> None:
    import torch
    from safetensors.torch import save_file

    directory.mkdir(parents=True, exist_ok=True)
    tensors = {f"model.{k}": v.contiguous() for k, v in policy.unet.state_dict().items()}
    tensors.update({f"ema.{k}": v.contiguous() for k, v in ema.shadow.items()})
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for index, state in ((i, optimizer.state[p]) for i, p in enumerate(params)):
        for key, value in state.items():
            tensors[f"optim.{index}.{key}"] = value.reshape(-1).contiguous() if key == "step" \
                else value.contiguous()
    tensors["rng.generator"] = generator.get_state()
    tensors["rng.torch"] = torch.get_rng_state()
    save_file(tensors, str(directory / "state.safetensors"))
    meta = {"step": step, "losses": losses, "policy": policy.config.to_dict()}
    (directory / "state.json").write_text(json.dumps(meta))


def load_checkpoint(directory: Path, policy: DiffusionPolicy, ema: EmaWeights,
                    optimizer: torch.optim.Optimizer, generator: torch.Generator,
                    device: torch.device | str = "cpu") -> tuple[int, list[float]]:
    """Continues a checkpoint on `device` (it is written from any device, read on any)."""
    import torch
    from safetensors.torch import load_file

    meta = json.loads((directory / "state.json").read_text())
    if meta["policy"] != json.loads(json.dumps(policy.config.to_dict())):
        raise ValueError(f"checkpoint in {directory} was made with another configuration")
    tensors = load_file(str(directory / "state.safetensors"))
    tensors = {k: v if k.startswith("rng.") or k.endswith(".step") else v.to(device)
               for k, v in tensors.items()}
    policy.unet.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    ema.shadow = {k[4:]: v for k, v in tensors.items() if k.startswith("ema.")}
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for index, param in enumerate(params):
        prefix = f"optim.{index}."
        state = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
        if state:
            state["step"] = state["step"].reshape(())
            optimizer.state[param] = state
    generator.set_state(tensors["rng.generator"])
    torch.set_rng_state(tensors["rng.torch"])
    return meta["step"], meta["losses"]


def plot_losses(losses: list[float], path: Path, title: str) -> None:
    import matplotlib
    import torch

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    window = max(1, len(losses) // 200)
    smooth = torch.tensor(losses).unfold(0, window, window).mean(1) if len(losses) >= window \
        else torch.tensor(losses)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(torch.arange(len(smooth)) * window, smooth)
    ax.set(xlabel="training step", ylabel="noise-prediction MSE", title=title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def starting_policy(args: argparse.Namespace, demos) -> DiffusionPolicy:
    """The network training starts from: fresh, or (`--init-from`) a trained policy's weights,
    made zone-aware with `--zones`: the condition's new inputs get zero weights, so the network
    starts as exactly the policy it was, and learns what the zones add."""
    import torch

    from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
    from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
    from constrained_diffusion_ros.policy.policy_config import PolicyConfig
    from constrained_diffusion_ros.policy.weights import load_policy

    zone_grid = ZONE_GRID if args.zones else 0
    if args.init_from is None:
        normalizer = {"obs": MinMaxNormalizer.fit(demos.observations).to_dict(),
                      "action": MinMaxNormalizer.fit(demos.actions).to_dict()}
        return DiffusionPolicy(PolicyConfig(down_dims=tuple(args.down_dims),
                                            normalizer=normalizer, zone_grid=zone_grid))
    trained = load_policy(args.init_from)
    config = dataclasses.replace(trained.config, zone_grid=zone_grid or trained.config.zone_grid)
    policy = DiffusionPolicy(config)
    state = policy.unet.state_dict()
    with torch.no_grad():
        for name, tensor in trained.unet.state_dict().items():
            target = state[name]
            target.zero_()
            target[tuple(slice(0, n) for n in tensor.shape)] = tensor
    return policy


def train(args: argparse.Namespace) -> dict:
    import torch
    from safetensors import SafetensorError
    from tqdm import tqdm

    from constrained_diffusion_ros.policy.weights import load_policy, save_policy
    from constrained_diffusion_ros.pusht import PUSHT_ROBOT
    from constrained_diffusion_ros.training.dataset import WindowSampler, load_demonstrations
    from constrained_diffusion_ros.training.zone_shapes import (
        ShapeBank,
        ZoneSampler,
        policy_routes,
    )
    from constrained_diffusion_ros.zones.raster import fine_cell_px

    device = use_compute_arguments(args)
    torch.manual_seed(args.seed)
    demos = load_demonstrations(args.dataset)
    policy = starting_policy(args, demos).to(device).train()
    config = policy.config
    sampler = WindowSampler(demos, config.horizon, config.n_obs_steps, config.n_action_steps)
    generator = torch.Generator().manual_seed(args.seed)
    zones = routes = None
    if config.sees_zones:
        bank = ShapeBank.build(SHAPES, args.seed, fine_cell_px(config.zone_workspace,
                                                               config.zone_grid),
                               PUSHT_ROBOT.pusher_radius)
        zones = ZoneSampler(bank, config.zone_grid, config.zone_workspace, args.zone_drop,
                            generator)
        if args.init_from is not None:
            with torch.inference_mode():
                routes = policy_routes(load_policy(args.init_from).to(device), sampler,
                                       ROUTES_PER_WINDOW, args.seed, quiet=args.quiet)
    ema = EmaWeights(policy.unet)
    optimizer = torch.optim.AdamW(policy.unet.parameters(), lr=args.lr, betas=(0.95, 0.999),
                                  weight_decay=1e-6)
    output = Path(args.output)
    checkpoint = output / CHECKPOINT_DIR
    step, losses = 0, []
    if args.resume and (checkpoint / "state.json").exists():
        try:
            step, losses = load_checkpoint(checkpoint, policy, ema, optimizer, generator,
                                           device)
        except (OSError, KeyError, TypeError, RuntimeError, SafetensorError,
                json.JSONDecodeError) as error:
            raise ValueError(f"checkpoint in {checkpoint} is damaged ({type(error).__name__}: "
                             f"{one_line(error, 200)}); remove it to start "
                             f"afresh") from None
        print(f"resumed from {checkpoint} at step {step}")
    n_params = sum(p.numel() for p in policy.unet.parameters())
    print(f"{len(demos.episode_ends)} episodes, {len(sampler)} windows, {n_params / 1e6:.1f}M "
          f"parameters, {args.steps} steps of batch {args.batch_size}")
    started = time.monotonic()
    order = torch.randperm(len(sampler), generator=generator)
    cursor = 0
    with tqdm(total=args.steps, initial=step, desc="training", unit="step",
              disable=args.quiet) as bar:
        while step < args.steps:
            if cursor + args.batch_size > len(order):
                order, cursor = torch.randperm(len(sampler), generator=generator), 0
            ids = order[cursor: cursor + args.batch_size]
            obs, actions = sampler.batch(ids)
            raster = None if zones is None else zones.rasters(
                torch.cat([obs[..., -2:], actions], dim=1), obs[:, -1, -2:],
                None if routes is None else routes[ids].cpu()).to(device)
            obs, actions = obs.to(device), actions.to(device)
            cursor += args.batch_size
            for group in optimizer.param_groups:
                group["lr"] = args.lr * cosine_with_warmup(step, args.warmup, args.steps)
            loss = policy.compute_loss(obs, actions, generator, raster)
            if not torch.isfinite(loss):  # NaN in the data or a diverged run: stop, save none
                raise ValueError(f"non-finite loss ({loss.item()}) at step {step + 1}; nothing "
                                 f"saved after the last checkpoint (check the dataset for "
                                 f"NaN, or lower --lr)")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            ema.update(policy.unet, step)
            step += 1
            losses.append(loss.item())
            bar.update(1)
            if step % 50 == 0:
                bar.set_postfix(loss=f"{sum(losses[-50:]) / 50:.4f}")
            if step % args.checkpoint_every == 0 or step == args.steps:
                save_checkpoint(checkpoint, step, policy, ema, optimizer, generator, losses)
    elapsed = time.monotonic() - started
    final_loss = sum(losses[-500:]) / len(losses[-500:])
    policy.unet.load_state_dict(ema.shadow)
    facts = {"training": {
        "command": " ".join(["train_policy", *sys.argv[1:]]), "steps": step,
        "batch_size": args.batch_size, "lr": args.lr, "seed": args.seed,
        "final_loss_mean_last_500": final_loss, "wall_time_s_this_run": round(elapsed, 1),
        "parameters": n_params, "episodes": len(demos.episode_ends),
        **({"init_from": str(args.init_from)} if args.init_from else {}),
        **({"zone_drop": args.zone_drop, "zone_shapes": SHAPES} if zones else {}),
    }}
    save_policy(policy, output, extra=facts)
    plot_losses(losses, output / "loss_curve.png", f"{n_params / 1e6:.1f}M-parameter U-Net")
    (output / "losses.json").write_text(json.dumps([round(x, 6) for x in losses]))
    print(f"saved EMA weights to {output}; final loss {final_loss:.4f}; {elapsed:.0f} s")
    return facts


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser("train_policy", __doc__.split("\n\n")[0])
    parser.add_argument("--dataset", required=True, help="path to pusht_cchi_v7_replay.zarr")
    parser.add_argument("--output", default="models/pusht_lowdim",
                        help="directory for weights, config, loss curve and checkpoint")
    parser.add_argument("--steps", type=positive_int, default=20000,
                        help="optimiser steps in total")
    parser.add_argument("--batch-size", type=positive_int, default=256)
    parser.add_argument("--lr", type=float, default=3e-4, help="peak learning rate (cosine)")
    parser.add_argument("--warmup", type=int, default=500, help="linear warm-up steps")
    parser.add_argument("--down-dims", type=positive_int, nargs="+", default=[64, 128, 256],
                        help="U-Net channel widths per level")
    parser.add_argument("--zones", action="store_true",
                        help="train a zone-aware policy: the zones in force join its "
                             "condition (shapes of many kinds placed so that each "
                             "demonstration keeps clear of them)")
    parser.add_argument("--zone-drop", type=float, default=0.25,
                        help="share of training windows given no zones, so the policy without "
                             "zones stays what it was")
    parser.add_argument("--init-from", default=None, metavar="POLICY_DIR",
                        help="start from this trained policy's weights (with --zones: made "
                             "zone-aware, starting exactly as it was); its architecture and "
                             "normaliser are kept, --down-dims ignored")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--checkpoint-every", type=positive_int, default=1000)
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a model already in --output (refused otherwise)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_compute_arguments(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    from constrained_diffusion_ros.policy.device import resolve_device
    from constrained_diffusion_ros.policy.weights import WEIGHTS_FILE

    output = Path(args.output)
    checkpoint = output / CHECKPOINT_DIR / "state.json"
    if args.resume and (output / WEIGHTS_FILE).exists() and not checkpoint.exists():
        raise ValueError(f"--resume: {output} holds a model but no checkpoint to continue "
                         f"(the shipped model has none); choose another --output")
    if (output / WEIGHTS_FILE).exists() and not (args.resume or args.overwrite):
        raise ValueError(f"{output} holds a model already; pass --resume to continue its "
                         f"checkpoint, --overwrite to replace it, or another --output")
    resolve_device(args.device)  # before anything is read or written
    try:
        train(args)
    except KeyboardInterrupt:
        print("train_policy: interrupted; rerun with --resume to continue from the last "
              "checkpoint", file=sys.stderr)
        return 130
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command(run, build_parser().parse_args(argv), "train_policy")


if __name__ == "__main__":
    sys.exit(main())
