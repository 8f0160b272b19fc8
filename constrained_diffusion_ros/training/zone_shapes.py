"""Zones to train a zone-aware policy with, placed so that each demonstration avoids them.

A bank of shapes of many kinds (posts, discs, walls, L, U, triangles, random star-shaped
polygons, concave ones among them) is drawn once, each in a local frame around its anchor. For
every training window, 0 to MAX_ZONES of them are placed by rejection: a candidate is kept only
if the window's pusher positions and its action chunk keep the pusher's disc clear of it. Where
candidates are drawn depends on the observation only, never on the chunk: then the chunks of the
windows a zone is kept for are the demonstrations' own, restricted to those that keep clear,
which is the constrained distribution the policy should learn (candidates drawn along the chunk
would teach that routes run beside zones). Half are anchored on the routes the trained policy
itself plans from the window's observation (`routes`, drawn once before training): such a zone
is kept only where the demonstration went another way than that route, so it teaches which way
to go when a zone blocks one; a zone anywhere else is mostly one the demonstration would have
kept clear of anyway. Of the rest, most are anchored near the pusher and some anywhere. A share
of windows (`drop`) gets none, so the network without zones stays the policy it was.

Everything a batch needs is a lookup in precomputed masks: the occupancy of each shape at the
raster's fine points (to paint the condition exactly as `zones/raster.py` samples real zones),
and at a finer grid its grown version (for the rejection).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
import shapely.affinity
import torch
from torch import Tensor

from constrained_diffusion_ros.zones.raster import SAMPLES_PER_SIDE, coverage_raster

KINDS = ("post", "disc", "wall", "L", "U", "triangle", "polygon")
MAX_ZONES = 4
FRAME_PX = 288.0  # side of a shape's local frame, centred on its anchor
REACH_PX = 120.0  # every shape lies within this of its anchor (it fits its frame, grown)
CHECK_PX = 4.0  # cell of the grown masks the rejection looks points up in
CHECK_SLACK_PX = 3.0  # grown by this beyond the disc: a point may sit anywhere in its cell
ON_ROUTE = 0.5  # share of candidates anchored on a route the policy plans (where there are)
ROUTE_PX = 40.0  # how far from a waypoint of that route such an anchor may be
NEAR_PUSHER = 0.6  # of the others, the share anchored near the pusher
NEAR_PX = 160.0  # how far from the pusher such an anchor may be
TRIES = 8  # candidates per zone of a window


def random_shape(kind: str, rng: np.random.Generator) -> shapely.Polygon:
    """One shape of `kind`, around the origin, at a random angle."""
    u = rng.uniform
    if kind == "post":
        side = u(20, 50)
        shape = shapely.box(-side / 2, -side / 2, side / 2, side / 2)
    elif kind == "disc":
        shape = shapely.Point(0, 0).buffer(u(10, 30), quad_segs=8)
    elif kind == "wall":
        length, width = u(80, 220), u(12, 30)
        shape = shapely.box(-length / 2, -width / 2, length / 2, width / 2)
    elif kind == "L":
        a, b, w = u(60, 160), u(60, 160), u(15, 30)
        shape = shapely.union(shapely.box(0, 0, a, w), shapely.box(0, 0, w, b))
    elif kind == "U":
        base, arm, w = u(100, 220), u(50, 110), u(15, 30)
        shape = shapely.union_all([shapely.box(0, 0, base, w), shapely.box(0, 0, w, arm),
                                   shapely.box(base - w, 0, base, arm)])
    elif kind == "triangle":
        angles = np.sort(rng.uniform(0, 2 * np.pi, 3))
        radii = rng.uniform(30, 90, 3)
        shape = shapely.Polygon(np.c_[radii * np.cos(angles), radii * np.sin(angles)])
    else:  # a star-shaped polygon: concave where a radius dips
        count = int(rng.integers(5, 10))
        angles = np.sort(rng.uniform(0, 2 * np.pi, count))
        radii = rng.uniform(20, 90, count)
        shape = shapely.Polygon(np.c_[radii * np.cos(angles), radii * np.sin(angles)])
    shape = shapely.affinity.rotate(shape, u(0, 360), origin="centroid")
    shape = shapely.affinity.translate(shape, -shape.centroid.x, -shape.centroid.y)
    extent = float(np.max(np.linalg.norm(np.asarray(shape.exterior.coords), axis=1)))
    if extent > REACH_PX:
        shape = shapely.affinity.scale(shape, REACH_PX / extent, REACH_PX / extent,
                                       origin=(0, 0))
    return shapely.make_valid(shape) if not shape.is_valid else shape


def cell_centres(cells: int, cell_px: float) -> tuple[np.ndarray, np.ndarray]:
    """x and y (cells x cells) of the centres of a local frame's cells, the anchor at 0."""
    centres = (np.arange(cells) + 0.5) * cell_px - FRAME_PX / 2
    y, x = np.meshgrid(centres, centres, indexing="ij")
    return x, y


@dataclass
class ShapeBank:
    """`count` shapes with their masks: `occupancy` (count, F, F) at the raster's fine points
    of a frame, `grown` (count, C, C) at CHECK_PX, grown by the pusher radius and slack."""

    shapes: list[shapely.Polygon]
    occupancy: Tensor
    grown: Tensor
    fine_px: float

    @classmethod
    def build(cls, count: int, seed: int, fine_px: float, pusher_radius: float) -> ShapeBank:
        rng = np.random.default_rng(seed)
        shapes = [random_shape(KINDS[i % len(KINDS)], rng) for i in range(count)]
        fine = round(FRAME_PX / fine_px)
        check = round(FRAME_PX / CHECK_PX)
        fx, fy = cell_centres(fine, fine_px)
        cx, cy = cell_centres(check, CHECK_PX)
        occupancy = np.stack([shapely.contains_xy(s, fx, fy) for s in shapes])
        grown = np.stack([shapely.contains_xy(s.buffer(pusher_radius + CHECK_SLACK_PX), cx, cy)
                          for s in shapes])
        return cls(shapes, torch.from_numpy(occupancy), torch.from_numpy(grown), fine_px)


class ZoneSampler:
    """Zone rasters for batches of training windows (see the module's docstring)."""

    def __init__(self, bank: ShapeBank, grid: int, workspace: tuple[float, ...],
                 drop: float, generator: torch.Generator) -> None:
        self.bank, self.grid, self.drop, self.generator = bank, grid, drop, generator
        self.origin = torch.tensor(workspace[:2], dtype=torch.float32)
        self.size = torch.tensor([workspace[2] - workspace[0], workspace[3] - workspace[1]],
                                 dtype=torch.float32)
        self.fine = grid * SAMPLES_PER_SIDE
        self.frame_cells = bank.occupancy.shape[-1]

    def _uniform(self, *shape: int) -> Tensor:
        return torch.rand(shape, generator=self.generator)

    def _around(self, centres: Tensor, reach: float) -> Tensor:
        """(B, TRIES, 2) points at most `reach` from `centres` (B, TRIES, 2), uniform in angle
        and distance."""
        angle = self._uniform(*centres.shape[:2]) * 2 * torch.pi
        distance = reach * self._uniform(*centres.shape[:2], 1)
        return centres + torch.stack([angle.cos(), angle.sin()], -1) * distance

    def _candidates(self, pusher: Tensor, routes: Tensor | None) -> tuple[Tensor, Tensor]:
        """For (B, 2) pusher positions and (B, W, 2) waypoints of the policy's routes (or
        None): (B, TRIES) shape ids and (B, TRIES, 2) frame corners, in whole fine cells from
        the workspace's origin."""
        batch = len(pusher)
        ids = torch.randint(len(self.bank.shapes), (batch, TRIES), generator=self.generator)
        near = self._around(pusher[:, None].expand(batch, TRIES, 2), NEAR_PX)
        anywhere = self.origin + self._uniform(batch, TRIES, 2) * self.size
        anchor = torch.where(self._uniform(batch, TRIES, 1) < NEAR_PUSHER, near, anywhere)
        if routes is not None:
            picked = routes[torch.arange(batch)[:, None], torch.randint(
                routes.shape[1], (batch, TRIES), generator=self.generator)]
            on_route = self._around(picked, ROUTE_PX)
            anchor = torch.where(self._uniform(batch, TRIES, 1) < ON_ROUTE, on_route, anchor)
        corner = torch.round((anchor - self.origin - FRAME_PX / 2) / self.bank.fine_px)
        return ids, corner.long()

    def _clear(self, path: Tensor, ids: Tensor, corner: Tensor) -> Tensor:
        """(B, TRIES) bool: the path keeps the disc clear of each candidate."""
        frame_px = corner.float() * self.bank.fine_px + self.origin  # (B, T, 2)
        local = ((path[:, None] - frame_px[:, :, None]) / CHECK_PX).floor().long()  # B,T,P,2
        cells = self.bank.grown.shape[-1]
        inside = ((local >= 0) & (local < cells)).all(-1)
        local = local.clamp(0, cells - 1)
        hit = self.bank.grown[ids[:, :, None], local[..., 1], local[..., 0]] & inside
        return ~hit.any(-1)

    def place(self, path: Tensor, pusher: Tensor, routes: Tensor | None = None
              ) -> tuple[Tensor, Tensor, Tensor]:
        """Zones for windows whose pusher path (its observed positions and its action chunk)
        is `path` (B, P, 2) px, whose pusher is at `pusher` (B, 2) now, and whose policy's
        routes pass `routes` (B, W, 2) (None: none known): (B, MAX_ZONES) shape ids,
        (B, MAX_ZONES, 2) frame corners in fine cells, and (B, MAX_ZONES) whether each slot
        holds a zone."""
        batch = len(path)
        wanted = torch.randint(1, MAX_ZONES + 1, (batch,), generator=self.generator)
        wanted[self._uniform(batch) < self.drop] = 0
        ids, corners, placed = [], [], []
        for slot in range(MAX_ZONES):
            candidates, corner = self._candidates(pusher, routes)
            clear = self._clear(path, candidates, corner) & (slot < wanted)[:, None]
            first = clear.float().argmax(1)
            ids.append(candidates[torch.arange(batch), first])
            corners.append(corner[torch.arange(batch), first])
            placed.append(clear.any(1))
        return torch.stack(ids, 1), torch.stack(corners, 1), torch.stack(placed, 1)

    def paint(self, ids: Tensor, corners: Tensor, placed: Tensor) -> Tensor:
        """(B, grid, grid) the coverage raster of the zones `place` gave."""
        rows, slots = torch.nonzero(placed, as_tuple=True)
        shape, (cx, cy) = ids[rows, slots], corners[rows, slots].T
        index, cells = torch.arange(self.fine), self.frame_cells
        ly = index[None, :, None] - cy[:, None, None]  # (n, fine, 1): rows of each frame
        lx = index[None, None, :] - cx[:, None, None]  # (n, 1, fine)
        valid = (ly >= 0) & (ly < cells) & (lx >= 0) & (lx < cells)
        mask = self.bank.occupancy[shape[:, None, None], ly.clamp(0, cells - 1),
                                   lx.clamp(0, cells - 1)] & valid
        canvas = torch.zeros(len(ids), self.fine, self.fine, dtype=torch.bool)
        canvas.index_put_((rows,), mask, accumulate=True)
        return coverage_raster(canvas, self.grid)

    def rasters(self, path: Tensor, pusher: Tensor, routes: Tensor | None = None) -> Tensor:
        """(B, grid, grid) zone rasters for windows (see `place`)."""
        return self.paint(*self.place(path, pusher, routes))


def policy_routes(policy, windows, per_window: int, seed: int, batch: int = 2048,
                  quiet: bool = False) -> Tensor:
    """(windows, per_window * n_action_steps, 2): the executed waypoints of `per_window` plans
    (DDIM 10, no zones) the trained `policy` makes from each window's observation, where
    `ZoneSampler` anchors zones that block a route the policy would take."""
    from tqdm import tqdm

    from constrained_diffusion_ros.sampling.sampler import DenoisingSampler

    config = policy.config
    sampler = DenoisingSampler(policy, "ddim", 10, "trailing")
    executed = slice(config.first_executed, config.first_executed + config.n_action_steps)
    generator = torch.Generator().manual_seed(seed)
    ids = torch.arange(len(windows)).repeat_interleave(per_window)
    routes = []
    for start in tqdm(range(0, len(ids), batch), desc="routes the policy plans", unit="batch",
                      disable=quiet):
        observations, _ = windows.batch(ids[start:start + batch])
        routes.append(sampler.sample(observations, generator)[:, executed])
    return torch.cat(routes).reshape(len(windows), -1, 2)
