"""Hand-made zones, denoising steps and observations shared by the sampling and planning tests."""

from __future__ import annotations

import numpy as np
import torch

from constrained_diffusion_ros.policy.modeling import DiffusionPolicy
from constrained_diffusion_ros.policy.normalizer import MinMaxNormalizer
from constrained_diffusion_ros.sampling.sampler import DenoisingStep
from constrained_diffusion_ros.zones import ZoneSet, rectangle

NORMALIZER = MinMaxNormalizer(torch.tensor([0.0, 0.0]), torch.tensor([512.0, 512.0]))
SQUARE = ZoneSet.from_polygons([rectangle(100, 100, 200, 200)])
L_SHAPE = ZoneSet.from_polygons([[[150, 150], [300, 150], [300, 200], [200, 200], [200, 330],
                                  [150, 330]]])
OVERLAPPING = ZoneSet.from_polygons([rectangle(60, 300, 260, 380), rectangle(200, 240, 300, 460)])
LEFT_BAND = ZoneSet.from_polygons([rectangle(0, 0, 256, 512)])
CENTRE = ZoneSet.from_polygons([rectangle(64, 64, 448, 448)])


def make_step(index: int, total: int = 5, seed: int = 7) -> DenoisingStep:
    return DenoisingStep(index=index, total=total, timestep=total - 1 - index,
                         generator=torch.Generator().manual_seed(seed), normalizer=NORMALIZER)


def observations(batch: int, seed: int = 1) -> torch.Tensor:
    return torch.rand(batch, 2, 20, generator=torch.Generator().manual_seed(seed)) * 512


def executed(policy: DiffusionPolicy, chunks: torch.Tensor) -> torch.Tensor:
    first = policy.config.first_executed
    return chunks[..., first: first + policy.config.n_action_steps, :]


def angle_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| for angles, in [0, pi]."""
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def chunk_of_rows(rows: int, length: int) -> np.ndarray:
    """(rows, length, 2): waypoint j of row r is (j, r), so a test reads off which it got."""
    index = np.arange(length, dtype=float)
    return np.stack([np.stack([index, np.full(length, float(r))], axis=-1) for r in range(rows)])
