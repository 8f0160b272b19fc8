"""Restricted-zone geometry, vectorised in torch over any batch shape of points.

Inference hooks keep diffusion waypoints out of restricted zones by asking a `RestrictedArea`
about whole action chunks at once, so every query takes points of shape (..., 2) in workspace px
and answers for all of them without Python loops.

`ZoneSet` implements it exactly for a union of polygons: shapely validates and merges the
polygons once, then the edges of the union's boundary rings are stored as tensors (E, 2)
(starts, directions, normals, ...) that every query broadcasts against. Rings are oriented so
the area always lies left of each edge (exteriors counter-clockwise, holes clockwise), which
gives every edge an outward normal and every segment crossing a direction (entering or leaving).

Precision: queries run in `ZoneSet.compute_dtype` (float64 by default) whatever the input dtype,
and results come back in the input dtype. float32 resolves only ~3e-5 px at 512 px, which makes
the even-odd test and distances near vertices noisy; set `compute_dtype = torch.float32` only on
accelerators that are slow at float64.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from functools import cached_property
from typing import NamedTuple

import numpy as np
import shapely
import torch
from numpy.typing import ArrayLike
from torch import Tensor

from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea

QUAD_SEGS = 16
"""Segments per quarter circle when inflating: arcs sag at most r * BUFFER_SAG ~ 0.1% r."""
BUFFER_SAG = 1.0 - math.cos(math.pi / (4 * QUAD_SEGS))
_FINE_QUAD_SEGS = 64  # for project_out's inflated area: about 0.01% of the margin too far


def rectangle(x_min: float, y_min: float, x_max: float, y_max: float) -> np.ndarray:
    """Vertices (4, 2) of an axis-aligned rectangle, counter-clockwise."""
    return np.array([[x_min, y_min], [x_max, y_min], [x_max, y_max], [x_min, y_max]], dtype=float)


def validate_polygon(vertices: ArrayLike, label: str = "polygon",
                     workspace: Bounds | None = None) -> shapely.Geometry:
    """Turn vertices (V, 2) into a valid shapely polygon the planner can enforce (clipped to
    `workspace` if given: several polygons if the clip splits it), or raise ValueError naming
    the fault.

    Checked here so that bad input is refused where it arrives, with `label` (e.g. "zone 'a'")
    in the message, instead of corrupting the union later.
    """
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{label}: vertices are not a numeric (V, 2) array ({error})") from None
    if v.ndim != 2 or v.shape[1] != 2:
        raise ValueError(f"{label}: expected vertices of shape (V, 2), got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"{label}: vertices must be finite, got NaN or inf")
    distinct = np.unique(v, axis=0)
    if len(distinct) < 3:
        raise ValueError(f"{label}: needs at least 3 distinct vertices, got {len(distinct)}")
    polygon = shapely.Polygon(v)
    reason = shapely.is_valid_reason(polygon)
    # Judged on the polygon, not by rank: a vertex at 1e30 swamps the others in a rank test
    # and calls a zone with hundreds of px^2 in the workspace collinear (the clip keeps them).
    if reason != "Valid Geometry":
        if np.linalg.matrix_rank(distinct - distinct.mean(axis=0)) < 2:
            raise ValueError(f"{label}: zero area, all vertices are collinear")
        raise ValueError(f"{label}: invalid polygon, {reason}")
    if workspace is not None:
        return clip_to_workspace(polygon, workspace, label)
    return check_enforceable(polygon, label)


MIN_ZONE_AREA = 1.0  # px^2: below it a zone is rounding noise (float32 vertices), not a region
MIN_ZONE_WIDTH = 0.5  # px: mean width, 2 area / perimeter (a band's width, half a square's)


def check_enforceable(polygon: shapely.Geometry, label: str) -> shapely.Geometry:
    """The polygon itself if the planner can enforce it: an area of at least `MIN_ZONE_AREA`,
    not a sliver (collinear points rounded to float32 make zero-area slivers that inflate to
    wide bands), and still a region when grown (huge coordinates make buffering return
    nothing); else ValueError naming the fault."""
    if polygon.area < MIN_ZONE_AREA:
        raise ValueError(f"{label}: area {polygon.area:.3g} px^2, below {MIN_ZONE_AREA:g}")
    if 2 * polygon.area / polygon.length < MIN_ZONE_WIDTH:
        raise ValueError(f"{label}: a sliver, narrower than {MIN_ZONE_WIDTH:g} px")
    if polygon.buffer(1.0).is_empty:
        raise ValueError(f"{label}: coordinates too large to grow the zone; keep them near the "
                         f"workspace")
    return polygon


def clip_to_workspace(polygon: shapely.Geometry, workspace: Bounds,
                      label: str = "polygon") -> shapely.Geometry:
    """The part of a zone inside the workspace (a zone reaching beyond it, even one covering
    everything, stays enforceable); ValueError if nothing, or only a sliver, is left."""
    x_min, y_min, x_max, y_max = workspace
    if shapely.within(polygon, shapely.box(x_min, y_min, x_max, y_max)):
        return check_enforceable(polygon, label)
    inside = shapely.intersection(shapely.box(x_min, y_min, x_max, y_max), polygon)
    parts = [part for part in shapely.get_parts(inside) if isinstance(part, shapely.Polygon)
             and not part.is_empty]
    if not parts:
        raise ValueError(f"{label}: lies outside the workspace {list(workspace)}")
    return check_enforceable(shapely.union_all(parts), f"{label} (inside the workspace)")


def leaves_no_room(zones: shapely.Geometry, workspace: Bounds, radius: float) -> bool:
    """Whether the zones grown by `radius` cover the whole workspace (no safe place for a pusher
    of that radius). Grown by r, k pieces of area A and perimeter P cover at most
    A + P r + k pi r^2: below the workspace's area there is room for sure, and nothing is
    grown (the zone callback is on the way to the safe setpoint)."""
    box = shapely.box(*workspace)
    pieces = len(shapely.get_parts(zones))
    if zones.area + zones.length * radius + pieces * math.pi * radius**2 < box.area:
        return False
    return bool(box.difference(zones.buffer(radius)).is_empty)


class _Edges(NamedTuple):
    """A set's edges as `_ring_edges` makes them, with each edge's ring and bounds (x_min,
    y_min, x_max, y_max), what `near` keeps or drops, and the coordinates' scale."""

    table: np.ndarray  # (E, 6, 2)
    ring_of_edge: np.ndarray  # (E,)
    bounds: np.ndarray  # (E, 4)
    scale: float


class _Columns(NamedTuple):
    """Every edge's start (ax, ay), direction (dx, dy), end's y, dy where it can divide, and
    squared length, each (E,)."""

    ax: Tensor
    ay: Tensor
    dx: Tensor
    dy: Tensor
    ay_end: Tensor
    dy_nonzero: Tensor  # dy, or 1 where it is 0
    length2: Tensor


class _Planes(NamedTuple):
    """`ZoneSet._planes`: points' x and y (..., 1), and y - each edge start's y (..., E)."""

    px: Tensor
    py: Tensor
    ry: Tensor


class _Outward(NamedTuple):
    """`ZoneSet._outward`: distance to the boundary, point - nearest boundary point, inside,
    the outward unit direction, on the boundary; with the vertices looked up, whether the
    nearest point is a vertex and that vertex's clearance step (else None)."""

    dist: Tensor
    away: Tensor
    inside: Tensor
    unit: Tensor
    on_boundary: Tensor
    at_vertex: Tensor | None
    vertex_step: Tensor | None


def _cross(u: Tensor, v: Tensor) -> Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _ring_edges(rings: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Edges of closed rings with the area on their left, as (E, 6, 2) rows: start, direction,
    outward unit normal, the clearance step at the start and at the end vertex, and the
    direction of the previous (incoming) edge; and the ring of each edge (E,). All rings at
    once: neighbours are found by index within each ring.

    The clearance step at a vertex is the direction (scaled) in which moving c from the vertex
    gives clearance c: the exterior bisector, lengthened by 1 / cos(half-angle) at reflex
    vertices, whose narrow exterior wedge only widens away from the tip.
    """
    if not rings:
        return np.zeros((0, 6, 2)), np.zeros(0, dtype=int)
    v = np.concatenate([r[:-1] for r in rings])
    ring = np.repeat(np.arange(len(rings)), [len(r) - 1 for r in rings])
    before, _ = _neighbours(ring)
    keep = np.any(v != v[before], axis=1)  # repeated vertices make no edge
    v, ring = v[keep], ring[keep]
    before, after = _neighbours(ring)
    d = v[after] - v
    normal = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
    bisector = normal + normal[before]  # outgoing + incoming edge at each start
    bisector /= np.maximum(np.linalg.norm(bisector, axis=1, keepdims=True), 1e-12)
    d_in = d[before]
    reflex = d_in[:, 0] * d[:, 1] - d_in[:, 1] * d[:, 0] < 0  # right turn: a notch in the area
    cos = np.maximum((bisector * normal).sum(axis=1, keepdims=True), 1e-9)
    step = np.where(reflex[:, None], bisector / cos, bisector)
    return np.stack([v, d, normal, step, step[after], d_in], axis=1), ring


def _neighbours(ring: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For vertices listed ring by ring (`ring`: each one's ring, ascending), the index of the
    previous and of the next vertex of the same ring, cyclically."""
    counts = np.bincount(ring)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])[ring]
    size, local = counts[ring], np.arange(len(ring)) - first
    return first + (local - 1) % size, first + (local + 1) % size


class ZoneSet(RestrictedArea):
    """An immutable union of polygons, queried in torch, with exact answers to every query.

    Overlapping or touching polygons merge into one region, so every answer (inside, distance,
    direction) refers to the union's boundary; points exactly on it may test either way.
    Queries broadcast points (..., 1) against all E edges, so memory grows as points x E; fine
    for action chunks against a few hundred edges. Edge tensors are cached per dtype and device.
    """

    compute_dtype: torch.dtype = torch.float64
    _inside_dropped = False  # a view of some rings (`near`): inside an odd number of the rest

    _caches = ("_derived_areas", "_tensors")

    def __init__(self, polygons: Iterable[shapely.Polygon] = ()) -> None:
        """Merge already valid shapely polygons; use `from_polygons` for raw vertex lists."""
        union = shapely.union_all([p for p in polygons if not p.is_empty])
        self._geometry = shapely.orient_polygons(union, exterior_cw=False)
        self._parts = [p for p in shapely.get_parts(self._geometry) if not p.is_empty]
        self._tensors: dict[tuple, tuple[Tensor, ...]] = {}  # per dtype and device

    @cached_property
    def _edges(self) -> _Edges:
        """Built at the first query, not with the set: a set only passed on to derive another
        (the bounded zones, inflated next) or read for its geometry never needs them."""
        rings = [np.asarray(r.coords) for p in self._parts for r in (p.exterior, *p.interiors)]
        table, ring_of_edge = _ring_edges(rings)
        ends = np.stack([table[:, 0], table[:, 0] + table[:, 1]])
        bounds = np.concatenate([ends.min(axis=0), ends.max(axis=0)], axis=1)
        return _Edges(table, ring_of_edge, bounds,
                      max(1.0, float(np.abs(table[:, 0]).max(initial=0.0))))

    @property
    def _table(self) -> np.ndarray:
        return self._edges.table

    @property
    def _ring_of_edge(self) -> np.ndarray:
        return self._edges.ring_of_edge

    @property
    def _edge_bounds(self) -> np.ndarray:
        return self._edges.bounds

    @property
    def _scale(self) -> float:
        return self._edges.scale

    @classmethod
    def from_polygons(cls, polygons: Sequence[ArrayLike]) -> ZoneSet:
        """Union of vertex arrays (V, 2), convex or concave; ValueError names any bad one."""
        return cls(validate_polygon(v, f"polygon {i}") for i, v in enumerate(polygons))

    @classmethod
    def empty(cls) -> ZoneSet:
        """A set with no zones: nothing is inside, every distance is +inf."""
        return cls()

    @property
    def geometry(self) -> shapely.Geometry:
        """The union as a shapely geometry (exteriors counter-clockwise)."""
        return self._geometry

    @property
    def polygons(self) -> list[np.ndarray]:
        """Exterior rings (V, 2) of the union's parts, unclosed, for drawing; holes are omitted."""
        return [np.asarray(p.exterior.coords)[:-1] for p in self._parts]

    @property
    def is_empty(self) -> bool:
        return not self._parts

    @property
    def area(self) -> float:
        return float(self._geometry.area)

    def __len__(self) -> int:
        """Number of disjoint polygons in the union (not of polygons given)."""
        return len(self._parts)

    def __repr__(self) -> str:
        return f"ZoneSet({len(self)} polygons, {len(self._table)} edges, area={self.area:.1f})"

    def buffer(self, radius: float, quad_segs: int = QUAD_SEGS) -> ZoneSet:
        """Minkowski sum with a disc (round joins), e.g. to keep a pusher of that radius out.

        A negative radius erodes instead. Arcs are polygons with vertices on the true circle,
        `quad_segs` segments per quarter circle. `inflate` gives the same, cached.
        """
        return self._like(shapely.get_parts(self._geometry.buffer(radius, quad_segs=quad_segs)))

    def near(self, points: Tensor, reach: float) -> ZoneSet:
        """The rings with an edge whose bounds come within `reach` of the points' bounding
        box. Every other ring is farther than `reach` from each point, so distances up to
        `reach` stay exact; and it does not meet the box, so the box lies wholly inside or
        outside it: its part in `contains` is the same for every point, counted once (the
        workspace frame's outer ring, around every point in the workspace, is such a ring).
        What moves points (projection, segments) and derived areas use the whole set."""
        p = torch.as_tensor(points).detach().reshape(-1, 2).cpu()
        if len(p) == 0 or self.is_empty:
            return self
        reach = max(float(reach), 0.0)
        corner = p.amin(dim=0).double().numpy()
        low, high = corner - reach, p.amax(dim=0).double().numpy() + reach
        bounds = self._edge_bounds
        touching = ((bounds[:, 0] <= high[0]) & (bounds[:, 2] >= low[0])
                    & (bounds[:, 1] <= high[1]) & (bounds[:, 3] >= low[1]))
        touched = np.zeros(self._ring_of_edge[-1] + 1, dtype=bool)  # rings ascend by edge
        touched[self._ring_of_edge[touching]] = True
        keep = touched[self._ring_of_edge]
        if keep.all() or not keep.any():  # nothing to drop, or nothing left to ask
            return self
        a, d = self._table[~keep, 0], self._table[~keep, 1]  # the dropped rings' edges
        straddle = (a[:, 1] > corner[1]) != (a[:, 1] + d[:, 1] > corner[1])
        x_cross = a[:, 0] + (corner[1] - a[:, 1]) * d[:, 0] / np.where(straddle, d[:, 1], 1.0)
        crossings = int((straddle & (corner[0] < x_cross)).sum())
        return _NearbyRings(self, keep, self._inside_dropped ^ bool(crossings % 2))

    def _like(self, polygons: Iterable[shapely.Polygon]) -> ZoneSet:
        """A new set of these polygons, computing in this set's dtype."""
        zones = ZoneSet(polygons)
        zones.compute_dtype = self.compute_dtype
        return zones

    def _inflated(self, radius: float) -> ZoneSet:
        return self.buffer(radius)

    def _bounded(self, workspace: Bounds) -> ZoneSet:
        return self._like([*shapely.get_parts(self._geometry), _frame(workspace)])

    # -- queries -------------------------------------------------------------------------------

    def contains(self, points: Tensor) -> Tensor:
        p, _ = self._prepare(points)
        if self.is_empty:
            return torch.zeros(p.shape[:-1], dtype=torch.bool, device=p.device)
        return self._inside(p)

    def signed_distance(self, points: Tensor) -> Tensor:
        p, dtype = self._prepare(points)
        distance = self._signed(p)
        # Inside stays negative in the caller's dtype too (float32 would round -tiny to -0.0).
        return torch.where(distance < 0, distance.to(dtype).clamp_max(-torch.finfo(dtype).tiny),
                           distance.to(dtype))

    def outward_direction(self, points: Tensor) -> Tensor:
        """Unit vectors (..., 2) that leave the area by the nearest boundary.

        Inside points get (nearest boundary point - point) normalised; outside points get
        (point - nearest boundary point), i.e. pointing away from the area: either way the
        gradient of `signed_distance`. Points on the boundary (within rounding) get the nearest
        edge's outward normal, or the exterior bisector at a vertex. An empty set answers
        zeros, since no direction is meaningful.
        """
        p, dtype = self._prepare(points)
        if self.is_empty:
            return torch.zeros_like(p).to(dtype)
        return self._outward(p).unit.to(dtype)

    def inside_and_outward(self, points: Tensor) -> tuple[Tensor, Tensor | None]:
        p, dtype = self._prepare(points)
        if self.is_empty:
            return torch.zeros(p.shape[:-1], dtype=torch.bool, device=p.device), None
        planes = self._planes(p)
        inside = self._inside(p, planes)
        if not inside.any():
            return inside, None
        return inside, self._outward(p, inside, planes=planes).unit.to(dtype)

    def project_out(self, points: Tensor, margin: float = 0.0, passes: int = 2) -> Tensor:
        """Move points inside, or less than `margin` outside, to clearance `margin`; keep others.

        Each such point goes to the nearest of a few candidates that are clear (checked after
        rounding to the input dtype), which guarantees nothing is left inside:
        - the exact one-step projection, nearest boundary point + `margin` outward (at a notch
          tip, along the notch): right wherever one edge or corner decides the answer; when it
          is clear and no longer than any move to that clearance can be, it is the answer
          (up to rounding) and the others are not computed;
        - `passes` projections onto the boundary of the area inflated by `margin` (arcs
          circumscribed, so ~0.01% of `margin` too far, more at sharp notches), then an exact step
          out of the original area to absorb shapely's buffer approximations: these solve
          concave corners and gaps narrower than 2 * margin, where one edge does not decide;
        - leaving the bounding box (grown by `margin`) by its nearest side: always clear, so
          the fallback when a slit defeats the others; far, but never inside.
        Points are pushed a few ulps beyond `margin` so that the cast back keeps them clear.
        """
        if margin < 0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        p, dtype = self._prepare(points)
        out = p.clone()
        if self.is_empty:
            return out.to(dtype)
        todo = self._signed(p) < margin
        if todo.any():
            out[todo] = self._clear(p[todo], margin, dtype, passes)
        return out.to(dtype)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        """Fraction t in [0, 1] of starts -> ends travelled before first entering the area.

        1.0 if the segment never enters (touching or sliding along the boundary is not
        entering), 0.0 if it starts inside. An entry is a crossing of an edge's interior from
        its outer side, or passing through a vertex into the interior angle there.
        """
        s, dtype = self._prepare(starts)
        e, _ = self._prepare(ends)
        s, e = torch.broadcast_tensors(s, e)
        if self.is_empty:
            return torch.ones(s.shape[:-1], dtype=dtype, device=s.device)
        a, d, _, _, _, d_in = self._edge_tensors(s.device, s.dtype)
        (ax, ay), (dx, dy), (ix, iy) = a.unbind(-1), d.unbind(-1), d_in.unbind(-1)
        rx, ry = e[..., None, 0] - s[..., None, 0], e[..., None, 1] - s[..., None, 1]
        qx, qy = ax - s[..., None, 0], ay - s[..., None, 1]  # edge starts seen from the start
        rr, length = rx * rx + ry * ry, d.norm(dim=-1)
        tol = 1024 * torch.finfo(s.dtype).eps * self._scale
        sin_tol = 1024 * torch.finfo(s.dtype).eps * rr.sqrt() * length

        # Through an edge's interior, from its right (outer) side to its left (the area).
        denom = rx * dy - ry * dx
        entering = denom < -sin_tol
        denom = torch.where(entering, denom, -1.0)
        t, u = (qx * dy - qy * dx) / denom, (qx * ry - qy * rx) / denom
        through_edge = entering & (t >= -tol) & (t <= 1)
        through_edge &= (u * length > tol) & ((1 - u) * length > tol)

        # Through a vertex: into the interior angle between the outgoing and incoming edges.
        tv = ((qx * rx + qy * ry) / torch.where(rr > 0, rr, 1.0)).clamp(0.0, 1.0)
        at_vertex = (tv * rx - qx) ** 2 + (tv * ry - qy) ** 2 <= tol**2
        left_of_out, left_of_in = dx * ry - dy * rx > sin_tol, ix * ry - iy * rx > sin_tol
        convex = _cross(d_in, d) >= 0
        into = torch.where(convex, left_of_out & left_of_in, left_of_out | left_of_in)

        first = torch.minimum(
            torch.where(through_edge, t, torch.inf), torch.where(at_vertex & into, tv, torch.inf)
        )
        first = first.amin(dim=-1).clamp(0.0, 1.0)
        return torch.where(self._inside(s), 0.0, first).to(dtype)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        """The segment enters the interior before its end (touching the boundary is allowed)."""
        return self.segment_clear_fraction(starts, ends) < 1.0

    # -- internals -------------------------------------------------------------------------------

    def _prepare(self, points: Tensor) -> tuple[Tensor, torch.dtype]:
        """Points in the compute dtype, plus the dtype to answer in."""
        points = torch.as_tensor(points)
        if points.shape[-1:] != (2,):
            raise ValueError(f"points must have shape (..., 2), got {tuple(points.shape)}")
        dtype = points.dtype if points.is_floating_point() else self.compute_dtype
        return points.to(self.compute_dtype), dtype

    def _edge_tensors(self, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, ...]:
        """The rows of `_ring_edges` for all rings, each (E, 2), on a device in a dtype."""
        key = (dtype, device)
        if key not in self._tensors:
            table = torch.as_tensor(self._table, dtype=dtype, device=device)
            self._tensors[key] = table.unbind(dim=1)
        return self._tensors[key]

    def _edge_columns(self, device: torch.device, dtype: torch.dtype) -> _Columns:
        """What the point queries read of every edge, as contiguous (E,) columns: taken once,
        not sliced (and the end's y and |d|^2 not recomputed) at every query."""
        key = ("columns", dtype, device)
        if key not in self._tensors:
            a, d, *_ = self._edge_tensors(device, dtype)
            ax, ay, dx, dy = (t.contiguous() for t in (a[:, 0], a[:, 1], d[:, 0], d[:, 1]))
            self._tensors[key] = _Columns(ax, ay, dx, dy, ay + dy, torch.where(dy != 0, dy, 1.0),
                                          (d * d).sum(dim=-1))
        return self._tensors[key]

    def _planes(self, p: Tensor) -> _Planes:
        """The points' x and y (..., 1), and their y seen from every edge's start (..., E):
        what the ray test and the distances share, taken once for both."""
        c = self._edge_columns(p.device, p.dtype)
        px, py = p.unsqueeze(-2).unbind(-1)
        return _Planes(px, py, py - c.ay)

    def _inside(self, p: Tensor, planes: _Planes | None = None) -> Tensor:
        """Even-odd ray test along +x against all edges (half-open at vertices)."""
        c = self._edge_columns(p.device, p.dtype)
        px, py, ry = self._planes(p) if planes is None else planes
        straddle = (c.ay > py) != (c.ay_end > py)
        # An edge that straddles has dy != 0; the others' crossings are not counted.
        x_cross = c.ax + ry * c.dx / c.dy_nonzero
        crossings = (straddle & (px < x_cross)).sum(dim=-1)
        return (crossings + 1 if self._inside_dropped else crossings) % 2 == 1

    def _offsets(self, p: Tensor, planes: _Planes | None = None
                 ) -> tuple[Tensor, Tensor, Tensor]:
        """(point - the nearest point of each edge) as x and y planes (..., E), and where on
        the edge that nearest point lies, t (..., E) (0: start vertex, 1: end vertex).
        Planes, not (..., E, 2): reductions over a size-2 axis are slow."""
        c = self._edge_columns(p.device, p.dtype)
        px, _, ry = self._planes(p) if planes is None else planes
        rx = px - c.ax
        t = ((rx * c.dx + ry * c.dy) / c.length2).clamp(0.0, 1.0)
        return rx - t * c.dx, ry - t * c.dy, t

    def _nearest(self, p: Tensor, planes: _Planes | None = None
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Distance to the boundary, (point - nearest boundary point), nearest edge, and where
        on that edge the nearest point lies (0: start vertex, 1: end vertex)."""
        wx, wy, t = self._offsets(p, planes)
        dist2, idx = (wx * wx + wy * wy).min(dim=-1)
        pick = idx.unsqueeze(-1)
        away = torch.cat([wx.gather(-1, pick), wy.gather(-1, pick)], dim=-1)
        return dist2.sqrt(), away, idx, t.gather(-1, pick).squeeze(-1)

    def _signed(self, p: Tensor) -> Tensor:
        if self.is_empty:
            return torch.full(p.shape[:-1], torch.inf, dtype=p.dtype, device=p.device)
        planes = self._planes(p)
        wx, wy, _ = self._offsets(p, planes)  # the distance only: no nearest edge picked
        dist = (wx * wx + wy * wy).amin(dim=-1).sqrt()
        # A boundary point the even-odd test counts inside is inside (negative), not at -0.0:
        # else project_out(margin=0) would leave it where `contains` still sees it.
        return torch.where(self._inside(p, planes),
                           -dist.clamp_min(torch.finfo(dist.dtype).tiny), dist)

    def _query(self, p: Tensor, inside: Tensor | None = None
               ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """For a non-empty set: signed distance (...), outward unit direction (..., 2), nearest
        boundary point (..., 2), and the step (..., 2) whose multiple c from that point gives
        clearance c (the unit direction, or a vertex's clearance step at notch tips).
        `inside`: `_inside(p)`, where the caller has it."""
        o = self._outward(p, inside, vertices=True)
        # Inside points nearest to a vertex face a notch tip: leave along the notch, not past it.
        step = torch.where(o.at_vertex & (o.on_boundary | o.inside[..., None]), o.vertex_step,
                           o.unit)
        return torch.where(o.inside, -o.dist, o.dist), o.unit, p - o.away, step

    def _outward(self, p: Tensor, inside: Tensor | None = None, vertices: bool = False,
                 planes: _Planes | None = None) -> _Outward:
        """The outward unit direction (`outward_direction`) and what it is made of. The
        nearest edge's vertex steps are looked up only with `vertices` or where a point lies
        on the boundary (where they decide the direction): a guidance hook asks at every
        denoising step, mostly about points off the boundary."""
        planes = self._planes(p) if planes is None else planes
        dist, away, idx, t = self._nearest(p, planes)
        inside = self._inside(p, planes) if inside is None else inside
        tol = 1024 * torch.finfo(p.dtype).eps * self._scale  # below this, `away` is mostly noise
        on_boundary = (dist <= tol)[..., None]
        vec = torch.where(inside[..., None], -away, away)
        unit = vec / dist[..., None].clamp_min(tol)
        if not (vertices or on_boundary.any()):
            return _Outward(dist, away, inside, unit, on_boundary, None, None)
        _, _, normal, start_step, end_step, _ = self._edge_tensors(p.device, p.dtype)
        at_vertex = ((t <= 0) | (t >= 1))[..., None]
        vertex_step = torch.where((t <= 0)[..., None], start_step[idx], end_step[idx])
        boundary_unit = torch.where(
            at_vertex, vertex_step / vertex_step.norm(dim=-1, keepdim=True), normal[idx]
        )
        unit = torch.where(on_boundary, boundary_unit, unit)
        return _Outward(dist, away, inside, unit, on_boundary, at_vertex, vertex_step)

    def _push(self, p: Tensor, clearance: float) -> Tensor:
        """One projection step: points with signed distance < clearance moved out to it."""
        return self._push_and_distance(p, clearance)[0]

    def _push_and_distance(self, p: Tensor, clearance: float) -> tuple[Tensor, Tensor]:
        """`_push`, and the signed distance of the points it started from."""
        sd, _, nearest, step = self._query(p)
        return torch.where((sd < clearance)[..., None], nearest + clearance * step, p), sd

    def _clear(self, p: Tensor, margin: float, dtype: torch.dtype, passes: int) -> Tensor:
        """The nearest clear candidate for points (N, 2) closer than margin (see project_out)."""
        eps = 16 * max(torch.finfo(dtype).eps, torch.finfo(p.dtype).eps) * (self._scale + margin)
        clearance = margin + eps
        one_step, signed = self._push_and_distance(p, clearance)
        # Reaching clearance `margin` takes a move of at least `margin` - distance (a distance
        # changes by at most the length moved): a clear one-step projection no longer than
        # that is the nearest clear point up to rounding, and needs no other candidate.
        shortest = (one_step - p).norm(dim=-1) <= clearance + eps - signed
        done = shortest & (self._signed(one_step.to(dtype).to(p.dtype)) >= margin)
        if done.all():
            return one_step
        out, p = one_step, p[~done]
        grown = self._inflated_for(margin)
        candidates, x = [one_step[~done]], p
        for _ in range(passes):
            x = self._push(grown._push(x, eps), clearance)
            candidates.append(x)
        candidates.append(self._box_exit(p, clearance))
        stack = torch.stack(candidates)  # (K, N, 2)
        clear = self._signed(stack.to(dtype).to(p.dtype)) >= margin
        clear[-1] = True  # the box exit is clear by construction
        cost = torch.where(clear, (stack - p).norm(dim=-1), torch.inf)
        best = cost.argmin(dim=0)
        out[~done] = stack[best, torch.arange(len(p), device=p.device)]
        return out

    def _inflated_for(self, margin: float) -> ZoneSet:
        """The area grown so its polygonal arcs stay >= margin away from this one (cached)."""
        if margin == 0:
            return self
        radius = margin / math.cos(math.pi / (4 * _FINE_QUAD_SEGS))
        return self._derived(("fine", margin), lambda: self.buffer(radius, _FINE_QUAD_SEGS))

    def _box_exit(self, p: Tensor, clearance: float) -> Tensor:
        """Nearest point on the bounding box grown by `clearance`: always clear of the area."""
        lo = torch.as_tensor(self._table[:, 0].min(axis=0) - clearance, dtype=p.dtype)
        hi = torch.as_tensor(self._table[:, 0].max(axis=0) + clearance, dtype=p.dtype)
        walls = torch.cat([lo, hi]).to(p.device)  # x_lo, y_lo, x_hi, y_hi
        gaps = torch.cat([p - walls[:2], walls[2:] - p], dim=-1)
        side = gaps.argmin(dim=-1, keepdim=True)
        return p.scatter(-1, side % 2, walls.expand_as(gaps).gather(-1, side))


class _NearbyRings(ZoneSet):
    """A query view of a ZoneSet that keeps only some rings' edges (see `ZoneSet.near`)."""

    def __init__(self, area: ZoneSet, rows: np.ndarray, inside_dropped: bool) -> None:
        """`rows`: the edges of `area` kept; `inside_dropped`: whether the points lie inside
        an odd number of the rings dropped (the same for every point: see `near`)."""
        self.__dict__.update(area.__dict__)
        self._whole = getattr(area, "_whole", area)
        self._inside_dropped = inside_dropped
        edges = area._edges
        self._edges = _Edges(edges.table[rows], edges.ring_of_edge[rows], edges.bounds[rows],
                             edges.scale)
        self._tensors = {}
        self._derived_areas = self._whole.__dict__.setdefault("_derived_areas", {})  # shared

    def project_out(self, points: Tensor, margin: float = 0.0, passes: int = 2) -> Tensor:
        return self._whole.project_out(points, margin, passes)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        return self._whole.segment_clear_fraction(starts, ends)


def _frame(workspace: Bounds) -> shapely.Polygon:
    """The outside of the workspace rectangle, out to its own size beyond each side."""
    x_min, y_min, x_max, y_max = workspace
    width, height = x_max - x_min, y_max - y_min
    outer = shapely.box(x_min - width, y_min - height, x_max + width, y_max + height)
    return outer.difference(shapely.box(x_min, y_min, x_max, y_max))

