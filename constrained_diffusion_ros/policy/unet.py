"""FiLM-conditioned 1D temporal U-Net (the ConditionalUnet1D of Diffusion Policy, Chi et al. 2023).

The noisy action chunk is a 1D signal over time; the diffusion step and the observation history
condition every residual block through a per-channel scale and bias (FiLM).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import torch
from torch import nn


class SinusoidalStepEmbedding(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, steps: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=steps.device) / (half - 1))
        angles = steps.float()[:, None] * freqs[None, :]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


def conv_block(channels_in: int, channels_out: int, kernel_size: int, n_groups: int) -> nn.Module:
    return nn.Sequential(
        nn.Conv1d(channels_in, channels_out, kernel_size, padding=kernel_size // 2),
        nn.GroupNorm(n_groups, channels_out),
        nn.Mish(),
    )


class FiLMResidualBlock(nn.Module):
    """Two conv blocks; the condition scales and shifts the features between them."""

    def __init__(self, channels_in: int, channels_out: int, cond_dim: int, kernel_size: int,
                 n_groups: int) -> None:
        super().__init__()
        self.first = conv_block(channels_in, channels_out, kernel_size, n_groups)
        self.second = conv_block(channels_out, channels_out, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * channels_out))
        self.skip = (nn.Conv1d(channels_in, channels_out, 1) if channels_in != channels_out
                     else nn.Identity())

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return self.filmed(x, self.film(cond))

    def filmed(self, x: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """The block with its FiLM output (B, 2 * channels_out) given."""
        scale, bias = film.unsqueeze(-1).chunk(2, dim=1)
        out = self.second(scale * self.first(x) + bias)
        return out + self.skip(x)


class ZoneEncoder(nn.Module):
    """A zone raster (B, grid, grid) -> (B, features): three strided 3 x 3 convolutions, then
    a linear layer over the 4 x 4 map they leave, for the condition of a zone-aware policy."""

    def __init__(self, features: int, channels: tuple[int, ...] = (16, 32, 64)) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for c_in, c_out in itertools.pairwise((1, *channels)):
            layers += [nn.Conv2d(c_in, c_out, 3, stride=2, padding=1), nn.Mish()]
        self.convolutions = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(4), nn.Flatten())
        self.linear = nn.Linear(16 * channels[-1], features)

    def forward(self, raster: torch.Tensor) -> torch.Tensor:
        return self.linear(self.convolutions(raster[:, None]))


class ConditionalUnet1D(nn.Module):
    """Predicts the noise in a (batch, horizon, action_dim) sample given step and global cond.

    A zone-aware network also holds the encoder of its zone raster (`zone_encoder`, trained
    with it and saved with its weights); the policy joins its output to the condition."""

    def __init__(self, action_dim: int, global_cond_dim: int, down_dims: tuple[int, ...],
                 kernel_size: int = 5, n_groups: int = 8, step_embed_dim: int = 256,
                 zone_features: int = 0) -> None:
        super().__init__()
        self.zone_encoder = ZoneEncoder(zone_features) if zone_features else None
        self.step_encoder = nn.Sequential(
            SinusoidalStepEmbedding(step_embed_dim),
            nn.Linear(step_embed_dim, 4 * step_embed_dim),
            nn.Mish(),
            nn.Linear(4 * step_embed_dim, step_embed_dim),
        )
        cond_dim = step_embed_dim + global_cond_dim

        def block(c_in: int, c_out: int) -> FiLMResidualBlock:
            return FiLMResidualBlock(c_in, c_out, cond_dim, kernel_size, n_groups)

        dims = [action_dim, *down_dims]
        pairs = list(itertools.pairwise(dims))
        self.down = nn.ModuleList()
        for index, (c_in, c_out) in enumerate(pairs):
            last = index == len(pairs) - 1
            resample = nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, 2, 1)
            self.down.append(nn.ModuleList([block(c_in, c_out), block(c_out, c_out), resample]))
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]) for _ in range(2)])
        self.up = nn.ModuleList()
        for c_in, c_out in reversed(pairs[1:]):  # every level upsamples; the finest skip is unused
            upsample = nn.ConvTranspose1d(c_in, c_in, 4, 2, 1)
            self.up.append(nn.ModuleList([block(2 * c_out, c_in), block(c_in, c_in), upsample]))
        self.head = nn.Sequential(
            conv_block(down_dims[0], down_dims[0], kernel_size, n_groups),
            nn.Conv1d(down_dims[0], action_dim, 1),
        )

    def forward(self, sample: torch.Tensor, steps: torch.Tensor,
                global_cond: torch.Tensor) -> torch.Tensor:
        # Sampling gives one step for the whole batch: embed it once, not once per row.
        embedded = self.step_encoder(steps.reshape(-1)).expand(sample.shape[0], -1)
        cond = torch.cat([embedded, global_cond], dim=-1)
        return self._walk(sample, lambda block, x: block(x, cond))

    def films(self, steps: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        """(T,) steps and (B, global_cond_dim) conditions -> (T, B, F): every residual block's
        FiLM scale and bias for each step, concatenated in `blocks` order: the sum of
        `step_films` and `condition_films`."""
        return self.step_films(steps)[:, None] + self.condition_films(global_cond)[None]

    def step_films(self, steps: torch.Tensor) -> torch.Tensor:
        """(T,) steps -> (T, F): the part of every block's FiLM output that comes from the
        step, with the biases. A block's FiLM is Linear(Mish([step embedding, condition])), and
        Mish acts on each value, so it splits into a part from the step and one from the
        condition: a runtime computes this part once per schedule and only the condition's
        (`condition_films`) per plan, then runs `forward_filmed` at each step."""
        linears = [block.film[-1] for block in self.blocks()]
        width = self.step_encoder[-1].out_features
        weight = torch.cat([linear.weight[:, :width] for linear in linears])
        bias = torch.cat([linear.bias for linear in linears])
        embedded = self.step_encoder(steps.reshape(-1))
        return torch.nn.functional.linear(torch.nn.functional.mish(embedded), weight, bias)

    def condition_films(self, global_cond: torch.Tensor,
                        weight: torch.Tensor | None = None) -> torch.Tensor:
        """(B, global_cond_dim) -> (B, F): the condition's part of every block's FiLM output
        (see `step_films`); `weight`: `condition_film_weight()`, if kept."""
        if weight is None:
            weight = self.condition_film_weight()
        return torch.nn.functional.linear(torch.nn.functional.mish(global_cond), weight)

    def condition_film_weight(self) -> torch.Tensor:
        """(F, global_cond_dim) the blocks' FiLM weights on the condition, concatenated."""
        width = self.step_encoder[-1].out_features
        return torch.cat([block.film[-1].weight[:, width:] for block in self.blocks()])

    def forward_filmed(self, sample: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """The noise predicted for `sample` given one step's `films` (B, F): each block takes
        its part in turn (`_walk` runs them in `blocks` order)."""
        parts = iter(film.split([block.film[-1].out_features for block in self.blocks()], dim=1))
        return self._walk(sample, lambda block, x: block.filmed(x, next(parts)))

    def blocks(self) -> list[FiLMResidualBlock]:
        """The residual blocks in the order the network runs them."""
        down = [block for first, second, _ in self.down for block in (first, second)]
        up = [block for first, second, _ in self.up for block in (first, second)]
        return [*down, *self.mid, *up]

    def _walk(self, sample: torch.Tensor, run: Callable[[FiLMResidualBlock, torch.Tensor],
                                                         torch.Tensor]) -> torch.Tensor:
        """The U-Net from the noisy sample (B, horizon, action_dim) to the noise, with `run`
        applying each residual block."""
        x = sample.transpose(1, 2)
        skips = []
        for first, second, downsample in self.down:
            x = run(second, run(first, x))
            skips.append(x)
            x = downsample(x)
        for mid in self.mid:
            x = run(mid, x)
        for first, second, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(run(second, run(first, x)))
        return self.head(x).transpose(1, 2)
