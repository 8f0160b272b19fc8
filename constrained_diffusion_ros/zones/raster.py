"""Zones as a zone-aware policy sees them: a coarse raster of how much of each cell they cover.

The network's condition has a fixed size whatever the zones are (any number, concave ones
included), so the zones in force go in as a `grid` x `grid` raster over the workspace: the
share of each cell covered, measured at SAMPLES_PER_SIDE^2 points per cell. Training paints
the same raster from masks of its own shapes (`training/zone_shapes.py`) through
`coverage_raster`, so what the network learned from and what it is given agree. The zones
themselves, not grown by the pusher: the network learns how far its disc must keep.
"""

from __future__ import annotations

import contextlib
import weakref

import torch
from torch import Tensor

from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea

SAMPLES_PER_SIDE = 2  # points per cell side where the zones are asked (their coverage)

_kept: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # area -> (key, raster)


def fine_cell_px(workspace: Bounds, grid: int) -> float:
    """The side of the cells whose centres `sample_points` gives (square cells)."""
    return (workspace[2] - workspace[0]) / (grid * SAMPLES_PER_SIDE)


def sample_points(workspace: Bounds, grid: int) -> Tensor:
    """(grid * S, grid * S, 2) the centres of the fine cells (S = SAMPLES_PER_SIDE per cell
    side), row i at y, column j at x, as `coverage_raster` pools them."""
    x0, y0, x1, y1 = workspace
    fine = grid * SAMPLES_PER_SIDE
    xs = x0 + (torch.arange(fine, dtype=torch.float64) + 0.5) * (x1 - x0) / fine
    ys = y0 + (torch.arange(fine, dtype=torch.float64) + 0.5) * (y1 - y0) / fine
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([x, y], dim=-1)


def coverage_raster(fine: Tensor, grid: int) -> Tensor:
    """(B, grid * S, grid * S) occupancy at the fine points -> (B, grid, grid) coverage."""
    return torch.nn.functional.avg_pool2d(fine.float()[:, None], SAMPLES_PER_SIDE)[:, 0]


def zone_raster(zones: RestrictedArea, batch: int, grid: int, workspace: Bounds) -> Tensor:
    """(batch, grid, grid) float32: the share of each cell `zones` cover, per row of a batch
    (a batch-aware area answers row by row). Kept with the area (areas are immutable): a
    planner asks again for every plan while the zones stay the same; a plug-in area that
    cannot be a weak key (unhashable, or slots without a weak reference) is rasterised anew."""
    key = (batch, grid, workspace)
    try:
        kept = _kept.get(zones)
    except TypeError:
        kept = None
    if kept is not None and kept[0] == key:
        return kept[1]
    points = sample_points(workspace, grid).reshape(1, -1, 2).expand(batch, -1, -1)
    inside = zones.signed_distance(points) < 0
    fine = grid * SAMPLES_PER_SIDE
    raster = coverage_raster(inside.reshape(batch, fine, fine), grid)
    with contextlib.suppress(TypeError):
        _kept[zones] = (key, raster)
    return raster
