"""The diffusion policy: U-Net plus the normalisers that put observations and actions in [-1, 1]."""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property
from typing import TYPE_CHECKING

import torch
from torch import nn

from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
from constrained_diffusion_ros.policy.policy_config import PolicyConfig
from constrained_diffusion_ros.policy.schedulers import make_scheduler
from constrained_diffusion_ros.policy.unet import ConditionalUnet1D

if TYPE_CHECKING:
    from diffusers import DDPMScheduler


def build_unet(config: PolicyConfig) -> ConditionalUnet1D:
    """The denoising network `config` describes, freshly initialised."""
    return ConditionalUnet1D(
        action_dim=config.action_dim,
        global_cond_dim=config.global_cond_dim,
        down_dims=config.down_dims,
        kernel_size=config.kernel_size,
        n_groups=config.n_groups,
        step_embed_dim=config.diffusion_step_embed_dim,
        zone_features=config.zone_features if config.sees_zones else 0,
    )


class DiffusionPolicy(nn.Module):
    """Predicts action chunks from an observation history by denoising (epsilon prediction)."""

    def __init__(self, config: PolicyConfig) -> None:
        super().__init__()
        if set(config.normalizer) != {"obs", "action"}:
            raise ValueError("policy config needs normaliser stats for 'obs' and 'action'")
        self.config = config
        self.unet = build_unet(config)
        self.obs_normalizer = MinMaxNormalizer.from_dict(config.normalizer["obs"])
        self.action_normalizer = MinMaxNormalizer.from_dict(config.normalizer["action"])
        # Where the network runs at inference when not in torch (inference.py's `use_runtime`):
        # (sample, one step's FiLM outputs) -> noise, as `unet.forward_filmed`; None: torch.
        self.fast: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
        # The FiLM's step part for one schedule and its weights on the condition, kept for a
        # fast runtime (`denoiser`).
        self._films: tuple[object, bytes, torch.Tensor, torch.Tensor] | None = None

    @cached_property
    def train_scheduler(self) -> DDPMScheduler:
        """The training noise schedule, built when training first asks: loading a policy to
        plan with does not import diffusers for it."""
        return make_scheduler(self.config, "ddpm")

    @property
    def device(self) -> torch.device:
        """Where the network's weights are (the CPU unless moved)."""
        return next(self.unet.parameters()).device

    def denoiser(self, timesteps: torch.Tensor, cond: torch.Tensor
                 ) -> Callable[[torch.Tensor, int], torch.Tensor]:
        """The network for one plan, at inference: (sample, index into `timesteps`) -> the
        predicted noise. On a fast runtime the FiLM outputs are the step's part, computed once
        per schedule and kept while the runtime is (its weights are frozen there too), plus
        the condition's, computed once per plan (`ConditionalUnet1D.step_films`)."""
        if self.fast is None:
            return lambda sample, index: self.unet(sample, timesteps[index], cond)
        fast, schedule = self.fast, timesteps.cpu().numpy().tobytes()
        kept = self._films
        if kept is None or kept[0] is not fast or kept[1] != schedule:  # one schedule kept
            kept = self._films = (fast, schedule, self.unet.step_films(timesteps),
                                  self.unet.condition_film_weight())
        steps, conditions = kept[2], self.unet.condition_films(cond, kept[3])
        return lambda sample, index: fast(sample, steps[index] + conditions)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_films": None}  # a planning process makes its own

    def condition(self, obs_history: torch.Tensor, zone_raster: torch.Tensor | None = None
                  ) -> torch.Tensor:
        """(B, n_obs_steps, obs_dim) raw observations -> (B, global_cond_dim) network condition.
        A zone-aware policy also encodes `zone_raster` (B, grid, grid) (zones/raster.py): the
        zones in force; None, no zones (an empty raster, as training drops the condition)."""
        expected = (self.config.n_obs_steps, self.config.obs_dim)
        if obs_history.ndim != 3 or tuple(obs_history.shape[1:]) != expected:
            raise ValueError(f"observation history must be (B, {expected[0]}, {expected[1]}), "
                             f"got {tuple(obs_history.shape)}")
        cond = self.obs_normalizer.normalize(obs_history.float()).flatten(1)
        if not self.config.sees_zones:
            return cond
        grid = self.config.zone_grid
        if zone_raster is None:
            zone_raster = torch.zeros(len(cond), grid, grid)
        if tuple(zone_raster.shape) != (len(cond), grid, grid):
            raise ValueError(f"zone raster must be ({len(cond)}, {grid}, {grid}), got "
                             f"{tuple(zone_raster.shape)}")
        zones = self.unet.zone_encoder(zone_raster.float().to(cond.device))
        return torch.cat([cond, zones], dim=1)

    def compute_loss(self, obs_history: torch.Tensor, actions: torch.Tensor,
                     generator: torch.Generator | None = None,
                     zone_raster: torch.Tensor | None = None) -> torch.Tensor:
        """The reference's training objective: MSE between true and predicted noise."""
        cond = self.condition(obs_history, zone_raster)
        clean = self.action_normalizer.normalize(actions)
        noise = torch.randn(clean.shape, generator=generator).to(clean.device)
        steps = torch.randint(0, self.config.num_train_timesteps, (clean.shape[0],),
                              generator=generator).to(clean.device)
        noisy = self.train_scheduler.add_noise(clean, noise, steps)
        return nn.functional.mse_loss(self.unet(noisy, steps, cond), noise)
