"""Different zones for different episodes of one batch, behind the same `RestrictedArea` API.

The evaluation batches every scenario of a configuration into one tensor, so row b of a batch
of points (B, ..., 2) is checked against `areas[assignment[b]]`. Each distinct area answers
for all of its rows at once: the loop runs over the few scenarios, never over episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea


class EpisodeZones(RestrictedArea):
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

    def signed_distance_after(self, points: Tensor, seconds: Tensor | float) -> Tensor:
        # `seconds` is the same for every row (no batch dimension of its own)
        return self._gather(lambda a, p: a.signed_distance_after(p, seconds), points)

    def outward_direction(self, points: Tensor) -> Tensor:
        return self._gather(lambda a, p: a.outward_direction(p), points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        return self._gather(lambda a, p: a.project_out(p, margin), points)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self._gather(lambda a, s, e: a.segment_clear_fraction(s, e), starts, ends)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self._gather(lambda a, s, e: a.crosses(s, e), starts, ends)

    def select_rows(self, rows: Tensor) -> EpisodeZones:
        """The episodes `rows`; an area that is batch-aware itself (a zone moved differently
        in each of its episodes) keeps the rows it answers for, in order."""
        rows = torch.as_tensor(rows)
        if rows.dtype == torch.bool:
            rows = torch.nonzero(rows).flatten()
        assignment = self.assignment[rows]
        rank = torch.empty_like(self.assignment)  # each episode's place among its area's
        for own in self._rows:
            rank[own] = torch.arange(len(own))
        areas = [area.select_rows(rank[rows[assignment == i]]) if (assignment == i).any()
                 else area for i, area in enumerate(self.areas)]
        return EpisodeZones(areas, assignment)

    def _inflated(self, radius: float) -> EpisodeZones:
        return EpisodeZones([a.inflate(radius) for a in self.areas], self.assignment)

    def _bounded(self, workspace: Bounds) -> EpisodeZones:
        return EpisodeZones([a.bounded(workspace) for a in self.areas], self.assignment)
