"""Different zones for different episodes of one batch, behind the same `RestrictedArea` API.

The evaluation batches every scenario of a configuration into one tensor, so row b of a batch
of points (B, ..., 2) is checked against `areas[assignment[b]]`. Each distinct area answers
for all of its rows at once: the loop runs over the few scenarios, never over episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import shapely
import torch
from torch import Tensor

from constrained_diffusion_ros.zones.geometry import RestrictedArea, ZoneSet


class EpisodeZones:
    """A batch-aware restricted area: one `RestrictedArea` per group of episodes."""

    def __init__(self, areas: Sequence[RestrictedArea], assignment: Sequence[int]) -> None:
        self.areas = list(areas)
        self.assignment = torch.as_tensor(assignment, dtype=torch.long)
        if self.assignment.ndim != 1 or len(self.assignment) == 0:
            raise ValueError("assignment must be a non-empty 1D list of area indices")
        if int(self.assignment.min()) < 0 or int(self.assignment.max()) >= len(self.areas):
            raise ValueError(f"assignment indices must be in [0, {len(self.areas)})")
        self._rows = [torch.nonzero(self.assignment == i).flatten()
                      for i in range(len(self.areas))]

    def __len__(self) -> int:
        return len(self.assignment)

    def _gather(self, query: Callable[..., Tensor], *batches: Tensor) -> Tensor:
        if batches[0].shape[0] != len(self):
            raise ValueError(f"expected a batch of {len(self)} episodes, "
                             f"got {batches[0].shape[0]}")
        out: Tensor | None = None
        for area, rows in zip(self.areas, self._rows):
            if len(rows) == 0:
                continue
            answer = query(area, *(b[rows] for b in batches))
            if out is None:
                out = answer.new_empty((len(self), *answer.shape[1:]))
            out[rows] = answer
        return out

    def contains(self, points: Tensor) -> Tensor:
        return self._gather(lambda a, p: a.contains(p), points)

    def signed_distance(self, points: Tensor) -> Tensor:
        return self._gather(lambda a, p: a.signed_distance(p), points)

    def outward_direction(self, points: Tensor) -> Tensor:
        return self._gather(lambda a, p: a.outward_direction(p), points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        return self._gather(lambda a, p: a.project_out(p, margin), points)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self._gather(lambda a, s, e: a.segment_clear_fraction(s, e), starts, ends)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self._gather(lambda a, s, e: a.crosses(s, e), starts, ends)

    def inflate(self, radius: float) -> EpisodeZones:
        return EpisodeZones([a.inflate(radius) for a in self.areas], self.assignment)


def select_rows(area: RestrictedArea, rows: Tensor) -> RestrictedArea:
    """The area that answers for rows `rows` of a batch: a batch-aware area keeps those rows'
    zones; any other area is the same for every row."""
    if isinstance(area, EpisodeZones):
        return EpisodeZones(area.areas, area.assignment[rows])
    return area


def bounded_area(area: RestrictedArea, size: float) -> RestrictedArea:
    """The area plus everything outside the [0, size]^2 workspace.

    Without it a zone touching a wall (the paper's left bands) has its wall side as a
    boundary, and "the nearest way out" would lead through the wall, off the workspace.
    """
    if isinstance(area, EpisodeZones):
        return EpisodeZones([bounded_area(a, size) for a in area.areas], area.assignment)
    if not isinstance(area, ZoneSet):
        return area  # a user's own check: its author decides what lies outside
    frame = shapely.box(-size, -size, 2 * size, 2 * size).difference(shapely.box(0, 0, size, size))
    bounded = ZoneSet([*shapely.get_parts(area.geometry), frame])
    bounded.compute_dtype = area.compute_dtype
    return bounded


def inflate_area(area: RestrictedArea, radius: float) -> RestrictedArea:
    """Grows an area by a radius when it knows how (ZoneSet, EpisodeZones); others are kept."""
    if radius <= 0:
        return area
    if isinstance(area, ZoneSet | EpisodeZones):
        return area.inflate(radius)
    raise ValueError(f"{type(area).__name__} cannot be inflated; implement inflate(radius)")
