"""Benchmark planning at batch 1 against the network's runtimes, all in one run.

For each torch thread count asked for (`--threads`, default 1 and 2) and each runtime (torch
eager; ONNX Runtime; with `--compile`, `torch.compile` where a C++ compiler is present), it
prints, each also as a ratio to torch eager in the same run:
  - one U-Net forward at batch 1 and at batch 25 (median of `--forwards`);
  - one plan at batch 1 with the body-safe hooks: DDIM 10 (`ddim10_r_g10_p_safe`) and DDPM 100
    (`r_g10_p_safe`), median of `--plans`, in a scene with the paper's 0.2 centre zone;
  - the same two samplers without hooks (`ddim10_none`, `none`): the network's and the
    sampler's part, a floor for the plans above on this machine;
  - the hooks' share of each plan: 1 - (the sampler without hooks) / (with them);
  - for a fast runtime, the torch operations one plan makes around the network: a count, which
    a machine's noise does not move as it moves the times.
Every fast path is first checked against torch on the same inputs (max abs difference of a
forward). The cells of a thread count are timed round-robin (a plan at a time, forwards
a tenth of them at a time, each visit after one untimed call), so a machine whose speed drifts
slows them alike. The shipped policy; run it on an idle machine.
Prints; asserts nothing.

  OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_planning.py
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.paths import config_dir, default_model_dir
from constrained_diffusion_ros.planning.constraint_configs import load_configurations
from constrained_diffusion_ros.planning.planners import ConstrainedPlanner
from constrained_diffusion_ros.policy import inference
from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.weights import load_policy
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from sim_bridge.scene import block_keypoints, observation, seeded_state

PLANS = {"DDIM 10 body-safe": "ddim10_r_g10_p_safe", "DDPM 100 body-safe": "r_g10_p_safe"}
UNHOOKED = {"DDIM 10 no hooks": "ddim10_none", "DDPM 100 no hooks": "none"}  # what the
# hooks add is the rest


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=str(default_model_dir()), help="policy directory")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                        help="torch (and ONNX Runtime) thread counts to measure at")
    parser.add_argument("--forwards", type=int, default=200, help="forwards timed per cell")
    parser.add_argument("--plans", type=int, default=15, help="DDIM plans timed per cell "
                        "(DDPM: a third as many, at least 3)")
    parser.add_argument("--compile", action="store_true",
                        help="also torch.compile (inductor; compiling takes tens of seconds)")
    return parser


@dataclass
class Cell:
    """One timed figure: `call` with the network on `fast` (None: torch eager), `count` times
    in visits of `burst` calls."""

    variant: str
    label: str
    fast: object
    call: Callable[[], object]
    count: int
    burst: int = 1
    times: list[float] = field(default_factory=list)

    @property
    def median_ms(self) -> float:
        return 1000 * statistics.median(self.times)


def time_round_robin(policy: DiffusionPolicy, cells: list[Cell]) -> None:
    """Times the cells in turn, a visit of each per round: one untimed call (the caches the
    cell before left it, refilled), then `burst` timed ones. A machine whose speed drifts, as
    a shared VM's does by tens of percent within minutes, then slows every cell alike, and
    the ratios and the hooks' shares hold."""
    try:
        for round_ in range(max(-(-cell.count // cell.burst) for cell in cells)):
            for cell in cells:
                timed = min(cell.burst, cell.count - round_ * cell.burst)
                if timed <= 0:
                    continue
                policy.fast = cell.fast
                cell.call()
                for _ in range(timed):
                    started = time.perf_counter()
                    cell.call()
                    cell.times.append(time.perf_counter() - started)
    finally:
        policy.fast = None


def scene_observation(seed: int = 100000) -> torch.Tensor:
    """(1, 2, obs_dim) the history of a seeded scene's first observation."""
    state = seeded_state(seed)
    obs = observation(block_keypoints(state[None, 2:])[0], state[:2])
    return torch.from_numpy(np.repeat(obs[None, None], 2, axis=1).astype(np.float32))


def compiled_denoiser(policy: DiffusionPolicy):
    """torch.compile's U-Net, or a reason it cannot be had here."""
    if shutil.which("c++") is None and shutil.which("g++") is None:
        return "no C++ compiler: inductor cannot build kernels here"
    try:
        compiled = torch.compile(inference.FilmedUnet(policy.unet),
                                 mode="max-autotune-no-cudagraphs")
    except Exception as error:  # a report, not a crash
        return f"{type(error).__name__}: {error}"
    return lambda sample, films: compiled(sample, films)  # not a submodule


@torch.inference_mode()
def cells_of(policy: DiffusionPolicy, name: str, fast: object, configs: dict,
             history: torch.Tensor, zones, args: argparse.Namespace) -> list[Cell]:
    """The cells of one runtime (`fast` on `policy`; None: torch eager), after its check
    against torch and, on a fast runtime, the torch operations each plan makes around the
    network (a count, which no machine's noise moves)."""
    config, cells, policy.fast = policy.config, [], fast
    try:
        for batch in (1, 25):
            sample = torch.randn(batch, config.horizon, config.action_dim)
            cond = torch.rand(batch, config.global_cond_dim) * 2 - 1
            timestep = torch.tensor([50])
            network = policy.denoiser(timestep, cond)  # a fast runtime's FiLM computed once
            if fast is not None and batch == 1:
                worst = float((network(sample, 0) - policy.unet(sample, timestep, cond))
                              .abs().max())
                print(f"  {name}: max abs difference from torch in a forward {worst:.1e}")
            cells.append(Cell(name, f"forward, batch {batch}", fast,
                              lambda s=sample, n=network: n(s, 0), args.forwards,
                              burst=max(1, args.forwards // 10)))
        for label, key in {**PLANS, **UNHOOKED}.items():
            planner = ConstrainedPlanner(policy, configs[key], PUSHT_ROBOT)
            generator = torch.Generator().manual_seed(0)
            count = args.plans if "DDIM" in label else max(3, args.plans // 3)
            cells.append(Cell(name, f"plan, {label}", fast,
                              lambda p=planner, g=generator: p.plan(history, zones, None, g),
                              count))
            if fast is not None:  # counted warm: caches a first plan builds are not a plan's
                planner.plan(history, zones, None, torch.Generator().manual_seed(0))
                ops = operations(lambda p=planner: p.plan(history, zones, None,
                                                          torch.Generator().manual_seed(0)))
                print(f"  {name:12s} {f'torch operations, {label}':32s} {ops:8d}")
    finally:
        policy.fast = None
    return cells


class _OperationCount(TorchDispatchMode):
    """Counts the torch operations dispatched while it is active."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        return func(*args, **(kwargs or {}))


def operations(call: Callable[[], object]) -> int:
    """How many torch operations one `call` makes."""
    with _OperationCount() as counter:
        call()
    return counter.count


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    policy = load_policy(args.model)
    configs = load_configurations(config_dir() / "configurations.yaml")
    zones = load_scenarios(config_dir() / "scenarios.yaml")["center_0.2"].zones_at(0)
    history = scene_observation()
    print(f"planning benchmark: {args.model}; torch {torch.__version__}; a scene with the 0.2 "
          f"centre zone; medians")
    for threads in args.threads:
        torch.set_num_threads(threads)
        variants: dict[str, object] = {"torch eager": None}
        inference.use_runtime(policy, "torch")
        chosen = inference.use_runtime(policy, "onnxruntime")
        variants["onnxruntime"] = policy.fast if chosen == "onnxruntime" else \
            "fell back to torch (see the log line above)"
        inference.use_runtime(policy, "torch")
        if args.compile:
            variants["torch.compile"] = compiled_denoiser(policy)
        print(f"\n== {threads} thread(s) ==")
        cells: list[Cell] = []
        for name, fast in variants.items():
            if isinstance(fast, str):
                print(f"  {name}: not measured ({fast})")
            else:
                cells += cells_of(policy, name, fast, configs, history, zones, args)
        with torch.inference_mode():
            time_round_robin(policy, cells)
        base = {cell.label: cell.median_ms for cell in cells if cell.fast is None}
        for name in dict.fromkeys(cell.variant for cell in cells):
            mine = {cell.label: cell.median_ms for cell in cells if cell.variant == name}
            for label, ms in mine.items():
                ratio = "" if name == "torch eager" else f"  ({ms / base[label]:.2f} x torch)"
                print(f"  {name:12s} {label:32s} {ms:8.2f} ms{ratio}")
            for plan, unhooked in zip(PLANS, UNHOOKED, strict=True):
                share = 1 - mine[f"plan, {unhooked}"] / mine[f"plan, {plan}"]
                print(f"  {name:12s} {f'hooks share, {plan}':32s} {100 * share:7.0f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
