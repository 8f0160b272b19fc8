"""What a restricted area is to the planner: one signed distance, and everything derived from it.

The hooks, the planners and the shield ask an area about whole batches of points (..., 2) in
workspace px: inside or not, how far, which way out, where the nearest clear point is, where a
straight segment first enters. They also derive new areas from it: grown by the pusher radius
(`inflate`), joined with the outside of the workspace (`bounded`), restricted to some rows of a
batch (`select_rows`). `RestrictedArea` gives every one of these a default built only on
`signed_distance`, so any check (a disc, a costmap, a learned model) subclasses it, implements
that one method and works with every configuration, the shield included. Exact geometry
(`ZoneSet`) overrides the defaults; derived areas are cached on the area they come from (areas
are immutable), which is the one place derived zone state is kept.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Sequence

import torch
from torch import Tensor

Bounds = tuple[float, float, float, float]  # x_min, y_min, x_max, y_max (px)

GRADIENT_STEP = 1e-4  # px: central differences of the signed distance
PROJECTION_PASSES = 8  # steps along the way out, for areas whose distance is not exact
MARCH_STEPS = 128  # sphere-tracing steps along a segment
TOUCH = 1e-6  # px: a segment this close to the area has reached it


class RestrictedArea(ABC):
    """A region the planner keeps actions out of; subclass it and implement `signed_distance`.

    The defaults are exact when `signed_distance` is the true Euclidean signed distance and
    conservative when it underestimates the distance outside (as a union's minimum does).
    """

    @abstractmethod
    def signed_distance(self, points: Tensor) -> Tensor:
        """(...): distance to the nearest boundary, negative inside, positive outside."""

    def contains(self, points: Tensor) -> Tensor:
        """Bool (...): the point lies inside the area."""
        return self.signed_distance(points) < 0

    def outward_direction(self, points: Tensor) -> Tensor:
        """(..., 2) unit vectors out by the nearest boundary (outside points: away from it);
        by default the normalised gradient of the signed distance (central differences)."""
        p = torch.as_tensor(points).to(torch.float64)
        dx = torch.tensor([GRADIENT_STEP, 0.0], dtype=torch.float64)
        dy = torch.tensor([0.0, GRADIENT_STEP], dtype=torch.float64)
        gradient = torch.stack([self.signed_distance(p + dx) - self.signed_distance(p - dx),
                                self.signed_distance(p + dy) - self.signed_distance(p - dy)],
                               dim=-1).to(torch.float64)
        unit = gradient / gradient.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return unit.to(_float_dtype(points))

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        """(..., 2): points with clearance below `margin` moved out to `margin`; others kept.

        By default up to `PROJECTION_PASSES` steps of (margin - distance) along the way out:
        one step for a true signed distance, a few where areas meet."""
        if margin < 0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        dtype = _float_dtype(points)
        p = torch.as_tensor(points).to(torch.float64)
        eps = 16 * torch.finfo(dtype).eps * (float(p.abs().max(initial=0.0)) + margin + 1.0)
        for _ in range(PROJECTION_PASSES):
            gap = margin + eps - self.signed_distance(p).to(torch.float64)
            todo = gap > eps
            if not todo.any():
                break
            step = gap[..., None] * self.outward_direction(p).to(torch.float64)
            p = torch.where(todo[..., None], p + step, p)
        return p.to(dtype)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        """(...): fraction t in [0, 1] of each segment travelled before it first enters the
        area (1.0: never, 0.0: starts inside). By default sphere tracing: step by the distance
        to the area, which never steps into it; a segment still marching after `MARCH_STEPS`
        is taken to enter where it got to."""
        dtype = _float_dtype(starts)
        s = torch.as_tensor(starts).to(torch.float64)
        e = torch.as_tensor(ends).to(torch.float64)
        s, e = torch.broadcast_tensors(s, e)
        delta, length = e - s, (e - s).norm(dim=-1)
        t = torch.zeros(s.shape[:-1], dtype=torch.float64)
        hit = self.contains(s)
        done = hit.clone()
        for _ in range(MARCH_STEPS):
            distance = self.signed_distance(s + t[..., None] * delta).to(torch.float64)
            hit |= ~done & (distance <= TOUCH)
            done |= hit
            t = torch.where(done, t, t + distance / length.clamp_min(1e-12))
            done |= t >= 1.0
            if done.all():
                break
        return t.clamp(0.0, 1.0).to(dtype)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        """Bool (...): the segment enters the area before its end."""
        return self.segment_clear_fraction(starts, ends) < 1.0

    # -- derived areas ---------------------------------------------------------------------------

    def inflate(self, radius: float) -> RestrictedArea:
        """The area grown by a disc of `radius` (negative: eroded), e.g. to keep a pusher's
        body out; cached."""
        if radius == 0:
            return self
        return self._derived(("inflate", float(radius)), lambda: self._inflated(float(radius)))

    def bounded(self, workspace: Bounds) -> RestrictedArea:
        """The area plus everything outside the workspace rectangle; cached.

        Without it a zone touching a wall (the paper's left bands) has its wall side as a
        boundary, and "the nearest way out" would lead through the wall, off the workspace."""
        key = ("bounded", tuple(map(float, workspace)))
        return self._derived(key, lambda: self._bounded(key[1]))

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        """The area that answers for rows `rows` of a batch; the same for every row unless the
        area is batch-aware (different zones per episode)."""
        return self

    def _inflated(self, radius: float) -> RestrictedArea:
        return Inflated(self, radius)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        from constrained_diffusion_ros.zones.geometry import outside_of

        return Union([self, outside_of(workspace)])

    def _derived(self, key: Hashable, build: Callable[[], RestrictedArea]) -> RestrictedArea:
        """Derived areas, kept on the instance: areas are immutable, so they never go stale."""
        cache = self.__dict__.setdefault("_derived_areas", {})
        if key not in cache:
            cache[key] = build()
        return cache[key]


class Inflated(RestrictedArea):
    """Any area grown by a disc: its signed distance minus the radius (exact for exact ones)."""

    def __init__(self, area: RestrictedArea, radius: float) -> None:
        self.area, self.radius = area, radius

    def signed_distance(self, points: Tensor) -> Tensor:
        return self.area.signed_distance(points) - self.radius

    def outward_direction(self, points: Tensor) -> Tensor:
        return self.area.outward_direction(points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        if margin + self.radius < 0:
            return super().project_out(points, margin)
        return self.area.project_out(points, margin + self.radius)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return self.area.select_rows(rows).inflate(self.radius)

    def _inflated(self, radius: float) -> RestrictedArea:
        return self.area.inflate(self.radius + radius)


class Union(RestrictedArea):
    """Several areas as one: inside any, the nearest boundary of the nearest one."""

    def __init__(self, parts: Sequence[RestrictedArea]) -> None:
        if not parts:
            raise ValueError("a union needs at least one area")
        self.parts = list(parts)

    def contains(self, points: Tensor) -> Tensor:
        return torch.stack([part.contains(points) for part in self.parts]).any(dim=0)

    def signed_distance(self, points: Tensor) -> Tensor:
        return torch.stack([part.signed_distance(points) for part in self.parts]).amin(dim=0)

    def outward_direction(self, points: Tensor) -> Tensor:
        distances = torch.stack([part.signed_distance(points) for part in self.parts])
        directions = torch.stack([part.outward_direction(points) for part in self.parts])
        nearest = distances.argmin(dim=0)[None, ..., None].expand(1, *directions.shape[1:])
        return directions.gather(0, nearest)[0]

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        fractions = [part.segment_clear_fraction(starts, ends) for part in self.parts]
        return torch.stack(fractions).amin(dim=0)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return Union([part.select_rows(rows) for part in self.parts])

    def _inflated(self, radius: float) -> RestrictedArea:
        return Union([part.inflate(radius) for part in self.parts])


def _float_dtype(points: Tensor) -> torch.dtype:
    points = torch.as_tensor(points)
    return points.dtype if points.is_floating_point() else torch.float64
