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

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Sequence

import torch
from torch import Tensor

Bounds = tuple[float, float, float, float]  # x_min, y_min, x_max, y_max (px)

GRADIENT_STEP = 1e-4  # px: central differences of the signed distance
PROJECTION_PASSES = 8  # steps along the way out, for areas whose distance is not exact
RAYS = 64  # directions searched for a clear point where those steps do not find one
RAY_STEPS = 256
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

    def signed_distance_after(self, points: Tensor, seconds: Tensor | float) -> Tensor:
        """(...): the signed distance, `seconds` (broadcast against points[..., 0]) from now,
        to everything the area may cover by then: a zone that moves may cover more than it
        does now (`zones.motion.MovingZones`); an area that stands still, itself."""
        return self.signed_distance(points)

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

    def inside_and_outward(self, points: Tensor) -> tuple[Tensor, Tensor | None]:
        """`contains(points)`, and `outward_direction(points)` where a point is inside (else
        None): what a push out needs, in one query where an area can answer both at once."""
        inside = self.contains(points)
        return inside, (self.outward_direction(points) if inside.any() else None)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        """(..., 2): points with clearance below `margin` moved out to `margin`; others kept.

        By default a step of (margin - distance) along the way out, exact for a true signed
        distance. Where one step is not enough (areas meet, and their ways out may face each
        other, as a zone's and a wall's), the nearer clear point of two: up to
        `PROJECTION_PASSES` such steps, or the nearest found along `RAYS` directions."""
        if margin < 0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        dtype = _float_dtype(points)
        start = torch.as_tensor(points).to(torch.float64)
        scale = float(start.abs().max()) if start.numel() else 0.0
        clearance = margin + 16 * torch.finfo(dtype).eps * (scale + margin + 1.0)
        p = self._step_out(start, clearance)
        hard = self._distance64(p) < clearance
        if hard.any():
            # Whole rows of the batch (a batch-aware area answers row by row), the rows
            # where a point is hard; of those, only the hard points change.
            if p.dim() >= 2:
                rows = torch.nonzero(hard.reshape(len(hard), -1).any(dim=1)).flatten()
                area = self.select_rows(rows)
            else:
                rows, area = slice(None), self
            stepped, begun, row_hard = p[rows], start[rows], hard[rows]
            for _ in range(PROJECTION_PASSES - 1):
                stepped = area._step_out(stepped, clearance)
            candidates = (stepped, area._nearest_clear_on_rays(begun, clearance))
            cost = torch.stack([torch.where(area._distance64(c) >= margin,
                                            (c - begun).norm(dim=-1), torch.inf)
                                for c in candidates])
            best = torch.where((cost[0] <= cost[1])[..., None], *candidates)
            p = p.clone()
            p[rows] = torch.where(row_hard[..., None], best, p[rows])
        return p.to(dtype)

    def _step_out(self, p: Tensor, clearance: float) -> Tensor:
        gap = clearance - self._distance64(p)
        step = gap[..., None] * self.outward_direction(p).to(torch.float64)
        return torch.where((gap > 0)[..., None], p + step, p)

    def _distance64(self, points: Tensor) -> Tensor:
        return self.signed_distance(points).to(torch.float64)

    def _nearest_clear_on_rays(self, points: Tensor, clearance: float) -> Tensor:
        """(..., 2) -> the nearest point with the clearance along RAYS directions from each; a
        point with no clear ray is kept. Steps of (clearance - distance) never pass the first
        clear point of a ray, since a distance changes by at most the length moved."""
        angles = torch.arange(RAYS, dtype=torch.float64) * (2 * math.pi / RAYS)
        rays = torch.stack([angles.cos(), angles.sin()], dim=-1)  # (K, 2)
        t = torch.zeros(*points.shape[:-1], RAYS, dtype=torch.float64)
        found = torch.zeros_like(t, dtype=torch.bool)
        for _ in range(RAY_STEPS):
            gap = clearance - self._distance64(points[..., None, :] + t[..., None] * rays)
            found |= gap <= 0
            best = torch.where(found, t, torch.inf).amin(dim=-1, keepdim=True)
            active = ~found & (t < best) & (t < 1e6)  # a ray that could still be nearer
            if not active.any():
                break
            t = torch.where(active, t + gap.clamp_min(1e-3), t)
        nearest = torch.where(found, t, torch.inf).min(dim=-1)
        moved = points + nearest.values[..., None] * rays[nearest.indices]
        return torch.where(found.any(dim=-1)[..., None], moved, points)

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

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        """An area that answers like this one for `points` (..., 2): the same `contains`, and
        the same signed distance wherever it is below `reach` (it may be larger beyond). Exact
        geometry drops the far edges, so checking many points near one pusher against many
        zones costs what the nearby zones cost; by default the area itself."""
        return self

    def _inflated(self, radius: float) -> RestrictedArea:
        return Inflated(self, radius)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        return AreaUnion([self, OutsideBox(workspace)])

    _caches: tuple[str, ...] = ("_derived_areas",)  # dicts rebuilt on demand, never pickled

    def __getstate__(self) -> dict:
        """Pickled (to the planning process) without what is derived and cached: it is rebuilt
        on demand, and it can be a hundred times the size of the zones themselves."""
        return {k: v for k, v in self.__dict__.items() if k not in self._caches}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__dict__.update({k: {} for k in self._caches})

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

    def signed_distance_after(self, points: Tensor, seconds: Tensor | float) -> Tensor:
        return self.area.signed_distance_after(points, seconds) - self.radius

    def outward_direction(self, points: Tensor) -> Tensor:
        return self.area.outward_direction(points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        if margin + self.radius < 0:
            return super().project_out(points, margin)
        return self.area.project_out(points, margin + self.radius)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return self.area.select_rows(rows).inflate(self.radius)

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        return Inflated(self.area.near(points, reach + self.radius), self.radius)

    def _inflated(self, radius: float) -> RestrictedArea:
        return self.area.inflate(self.radius + radius)


class Translated(RestrictedArea):
    """An area moved by `offset`: (2,) for every row, or (B, 2), one per row of a batch (a
    hand's zone at a different place in each episode). Queries shift the points back, so the
    area's exact geometry (and its caches) serve every offset."""

    def __init__(self, area: RestrictedArea, offset: Tensor) -> None:
        self.area = area
        self.offset = torch.as_tensor(offset, dtype=torch.float64)

    def _shift(self, points: Tensor) -> Tensor:
        points = torch.as_tensor(points)
        offset = self.offset.to(_float_dtype(points))
        if offset.dim() == 2:  # per row: (B, 2) against (B, ..., 2)
            offset = offset.reshape(len(offset), *([1] * (points.dim() - 2)), 2)
        return offset

    def signed_distance(self, points: Tensor) -> Tensor:
        return self.area.signed_distance(points - self._shift(points))

    def contains(self, points: Tensor) -> Tensor:
        return self.area.contains(points - self._shift(points))

    def outward_direction(self, points: Tensor) -> Tensor:
        return self.area.outward_direction(points - self._shift(points))

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        shift = self._shift(points)
        return self.area.project_out(points - shift, margin) + shift

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        shift = self._shift(starts)
        return self.area.segment_clear_fraction(starts - shift, ends - shift)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        offset = self.offset[rows] if self.offset.dim() == 2 else self.offset
        return Translated(self.area.select_rows(rows), offset)

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        return Translated(self.area.near(points - self._shift(points), reach), self.offset)

    def _inflated(self, radius: float) -> RestrictedArea:
        return Translated(self.area.inflate(radius), self.offset)


class OutsideBox(RestrictedArea):
    """Everything outside an axis-aligned rectangle (the workspace), with its exact distance."""

    def __init__(self, bounds: Bounds) -> None:
        self.bounds = tuple(map(float, bounds))

    def signed_distance(self, points: Tensor) -> Tensor:
        p = torch.as_tensor(points)
        x_min, y_min, x_max, y_max = self.bounds
        low = torch.tensor([x_min, y_min], dtype=p.dtype)
        high = torch.tensor([x_max, y_max], dtype=p.dtype)
        inside_margin = torch.minimum(p - low, high - p).amin(dim=-1)
        beyond = torch.maximum(low - p, p - high).clamp_min(0.0).norm(dim=-1)
        return torch.where(inside_margin >= 0, inside_margin, -beyond)


class AreaUnion(RestrictedArea):
    """Several areas as one: inside any, the nearest boundary of the nearest one."""

    def __init__(self, parts: Sequence[RestrictedArea]) -> None:
        if not parts:
            raise ValueError("a union needs at least one area")
        self.parts = list(parts)

    def contains(self, points: Tensor) -> Tensor:
        return torch.stack([part.contains(points) for part in self.parts]).any(dim=0)

    def signed_distance(self, points: Tensor) -> Tensor:
        return torch.stack([part.signed_distance(points) for part in self.parts]).amin(dim=0)

    def signed_distance_after(self, points: Tensor, seconds: Tensor | float) -> Tensor:
        return torch.stack([part.signed_distance_after(points, seconds)
                            for part in self.parts]).amin(dim=0)

    def outward_direction(self, points: Tensor) -> Tensor:
        distances = torch.stack([part.signed_distance(points) for part in self.parts])
        directions = torch.stack([part.outward_direction(points) for part in self.parts])
        nearest = distances.argmin(dim=0)[None, ..., None].expand(1, *directions.shape[1:])
        return directions.gather(0, nearest)[0]

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        fractions = [part.segment_clear_fraction(starts, ends) for part in self.parts]
        return torch.stack(fractions).amin(dim=0)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return AreaUnion([part.select_rows(rows) for part in self.parts])

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        return AreaUnion([part.near(points, reach) for part in self.parts])

    def _inflated(self, radius: float) -> RestrictedArea:
        return AreaUnion([part.inflate(radius) for part in self.parts])


def _float_dtype(points: Tensor) -> torch.dtype:
    points = torch.as_tensor(points)
    return points.dtype if points.is_floating_point() else torch.float64
