"""The denoising loop, batched over episodes, with hooks that act after every update.

Hooks see the sample in workspace pixels (the action space) and may change it; they never see
the network. This is the single place where the constraint hooks meet the diffusion model, so
training, evaluation and the ROS node all sample through it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import torch

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
from constrained_diffusion_ros.policy.schedulers import (
    SchedulerKind,
    TimestepSpacing,
    make_scheduler,
)
from constrained_diffusion_ros.sampling.updates import Noising, ScheduledUpdates
from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.raster import zone_raster


@dataclass(frozen=True)
class DenoisingStep:
    """Where the loop is: hooks use it for step-dependent weights and for their randomness."""

    index: int  # 0 for the first denoising update, total - 1 for the last
    total: int
    timestep: int
    generator: torch.Generator | None
    normalizer: MinMaxNormalizer  # action normaliser: workspace px <-> [-1, 1]
    next_timestep: int | None = None  # the noise level the sample is at now; None: clean
    noising: Noising | None = None  # the scheduler's add_noise at that level

    @property
    def progress(self) -> float:
        """0.0 after the first update, 1.0 after the last."""
        return self.index / max(1, self.total - 1)

    def noised(self, clean: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Workspace-pixel actions as a sample at this point of the loop holds them: clean
        ones noised (with `noise`, in the normalised space) to the level the update reached;
        unchanged after the last update."""
        if self.noising is None:  # after the last update (or a step made by hand)
            return clean
        return self.normalizer.unnormalize(self.noising(self.normalizer.normalize(clean), noise))


class SampleHook(Protocol):
    def __call__(self, sample: torch.Tensor, step: DenoisingStep) -> torch.Tensor:
        """(B, horizon, 2) workspace-pixel sample in, the same shape out."""
        ...


class Interrupted(Exception):
    """A sample stopped before its end: its result was no longer wanted."""


class DenoisingSampler:
    """Draws action chunks from a policy with DDPM (the reference) or DDIM (fewer steps)."""

    def __init__(self, policy: DiffusionPolicy, kind: SchedulerKind = "ddpm",
                 num_inference_steps: int | None = None,
                 timestep_spacing: TimestepSpacing = "leading", eta: float = 0.0,
                 zone_guidance: float = 1.0) -> None:
        """`eta` (DDIM only): 0 is deterministic given the first noise, 1 adds DDPM's noise
        at every step. `zone_guidance` (a zone-aware policy, zones given): the noise is the
        blind prediction plus this times what the zones change in it (classifier-free
        guidance: the network was trained with and without them); 1 is the prediction with
        the zones alone, more pushes plans further from them, at twice the network's rows."""
        self.policy, self.zone_guidance = policy, zone_guidance
        self.kind = kind
        self.scheduler = make_scheduler(policy.config, kind, timestep_spacing)
        self.num_inference_steps = num_inference_steps or policy.config.num_train_timesteps
        if not 1 <= self.num_inference_steps <= policy.config.num_train_timesteps:
            raise ValueError(f"num_inference_steps must be in [1, "
                             f"{policy.config.num_train_timesteps}], got {num_inference_steps}")
        self.scheduler.set_timesteps(self.num_inference_steps)
        self.updates = ScheduledUpdates(self.scheduler, eta)  # its `step`, without the overhead
        self._interrupt: Callable[[], bool] | None = None

    @contextlib.contextmanager
    def interruptible(self, interrupt: Callable[[], bool]) -> Iterator[None]:
        """Within the block `interrupt()` is asked before each denoising step, and True stops
        the sample with `Interrupted`: a planning worker's plan in flight that a zone or a new
        configuration made worthless ends at once rather than after its last step."""
        self._interrupt = interrupt
        try:
            yield
        finally:
            self._interrupt = None

    def _guided(self, network: Callable[[torch.Tensor, int], torch.Tensor]
                ) -> Callable[[torch.Tensor, int], torch.Tensor]:
        """`network` over (with zones, without) conditions -> classifier-free guided noise."""
        weight = self.zone_guidance

        def guided(sample: torch.Tensor, index: int) -> torch.Tensor:
            seeing, blind = network(torch.cat([sample, sample]), index).chunk(2)
            return blind + weight * (seeing - blind)

        return guided

    @torch.no_grad()
    def sample(self, obs_history: torch.Tensor, generator: torch.Generator | None = None,
               hooks: Sequence[SampleHook] = (), zones: RestrictedArea | None = None,
               seen_by: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n_obs_steps, obs_dim) observations -> (B, horizon, action_dim) workspace actions.
        A zone-aware policy plans with `zones` (batch-aware or one for all rows) in its
        condition, on the rows `seen_by` (bool (B,); None: all); any other policy ignores them
        (the hooks are what keep a plan out of them)."""
        config, normalizer = self.policy.config, self.policy.action_normalizer
        device = self.policy.device  # the network's; noise and hooks stay on the CPU
        raster = None
        if zones is not None and config.sees_zones:
            raster = zone_raster(zones, len(obs_history), config.zone_grid,
                                 config.zone_workspace)
            if seen_by is not None:
                raster = raster * seen_by.reshape(-1, 1, 1)
        cond = self.policy.condition(obs_history, raster).to(device)
        shape = (cond.shape[0], config.horizon, config.action_dim)
        sample = torch.randn(shape, generator=generator).to(device)
        timesteps = self.scheduler.timesteps
        guided = raster is not None and self.zone_guidance != 1.0
        if guided:  # one batch: the rows with the zones, then the same rows without
            cond = torch.cat([cond, self.policy.condition(obs_history).to(device)])
        network = self.policy.denoiser(timesteps.to(device), cond)
        if guided:
            network = self._guided(network)
        levels = [*timesteps.tolist(), None]  # after update i the sample is at level i + 1
        for index in range(len(timesteps)):
            if self._interrupt is not None and self._interrupt():
                raise Interrupted(f"stopped before denoising step {index + 1} of "
                                  f"{len(timesteps)}")
            noise = network(sample, index)
            sample = self.updates.apply(index, noise, sample, generator)
            if hooks:
                step = DenoisingStep(index, len(timesteps), levels[index], generator, normalizer,
                                     levels[index + 1], self.updates.noising[index])
                workspace = normalizer.unnormalize(sample.cpu())
                for hook in hooks:
                    workspace = hook(workspace, step)
                sample = normalizer.normalize(workspace).to(device)
        return normalizer.unnormalize(sample.cpu())
