"""Keep-out grids: zones given as an occupancy mask, as nav2's keep-out filter takes them.

The mask follows `nav_msgs/msg/OccupancyGrid`: int8 values in [-1, 100] (-1 unknown, which a
keep-out filter treats as free), row-major from row 0, `width` x `height` cells of side
`resolution` (px per cell here, since the workspace frame is in px), and `origin` (x, y) the
corner of cell (0, 0). Cell (row i, col j) covers x in [ox + j res, ox + (j + 1) res] and y in
[oy + i res, oy + (i + 1) res]; with the workspace's y down, row 0 is the top of the mask. A cell
whose value is at least `threshold` (65 by default, nav2 map_server's occupied_thresh 0.65) is
keep-out.

`grid_polygons` turns a mask into exact polygons (the union of its keep-out cells), so a grid
zone gets the same exact `ZoneSet` answers as a drawn one; `rasterize` goes the other way, to
build a mask from polygons; `read_pgm` reads a map image as map_server saves it.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import shapely
from numpy.typing import ArrayLike

from constrained_diffusion_ros.zones.area import Bounds
from constrained_diffusion_ros.zones.geometry import validate_polygon

KEEPOUT = 100  # the value `rasterize` writes in keep-out cells
DEFAULT_THRESHOLD = 65  # nav2 map_server's occupied_thresh 0.65, in OccupancyGrid percent


@dataclass(frozen=True)
class MaskCaps:
    """What a keep-out mask may cost, checked before the expensive step it bounds.

    A mask's pieces become zones the planner, the shield and the no-free-space check rebuild
    derived areas from (inflation, the union): their cost grows with pieces and vertices, so a
    fine checkerboard would stall the node for minutes. `cells` bounds the scan of the mask,
    `rectangles` the union that merges its cell runs, `pieces` and `vertices` (summed over the
    pieces) what the node then holds in force; `scripts/bench_zones.py` times them.
    """

    cells: int = 4096 * 4096
    rectangles: int = 4096
    pieces: int = 32
    vertices: int = 1024


def _mask(values: ArrayLike, width: int | None, height: int | None) -> np.ndarray:
    """(H, W) int16 from a 2-D array, or from a flat row-major array with width and height."""
    grid = np.asarray(values)
    if grid.ndim == 1:
        if width is None or height is None:
            raise ValueError("a flat grid needs width and height")
        if grid.size != width * height:
            raise ValueError(f"a flat grid of {grid.size} values is not {width} x {height}")
        grid = grid.reshape(height, width)
    elif grid.ndim != 2:
        raise ValueError(f"grid values must be (H, W) or flat, got shape {grid.shape}")
    elif (width is not None and grid.shape[1] != width) or (
            height is not None and grid.shape[0] != height):
        raise ValueError(f"grid of shape {grid.shape} is not {width} x {height} (W x H)")
    if grid.size and not np.issubdtype(grid.dtype, np.integer):
        raise ValueError(f"grid values must be integers, got {grid.dtype}")
    if grid.size and (grid.min() < -1 or grid.max() > 100):  # before narrowing: no wrap-around
        raise ValueError("grid values must lie in [-1, 100] (OccupancyGrid)")
    return grid.astype(np.int16)


def _check_cells(resolution: float, origin: Sequence[float]) -> tuple[float, float, float]:
    res = float(resolution)
    if not (np.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number of px per cell, got {resolution}")
    ox, oy = map(float, origin)
    if not (np.isfinite(ox) and np.isfinite(oy)):
        raise ValueError(f"origin must be finite, got {origin}")
    return res, ox, oy


def _rectangles(keepout: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Keep-out cells as rectangles (row0, row1, col0, col1), end-exclusive: runs of cells per
    row, and a run continued downwards while the next row has the very same run (few shapes to
    union for blocky masks)."""
    open_runs: dict[tuple[int, int], int] = {}  # (col0, col1) -> first row
    done = []
    for i, row in enumerate(keepout):
        edges = np.flatnonzero(np.diff(np.concatenate([[False], row, [False]]).astype(np.int8)))
        runs = set(zip(edges[::2].tolist(), edges[1::2].tolist()))
        for run in sorted(set(open_runs) - runs):
            done.append((open_runs.pop(run), i, *run))
        for run in sorted(runs - set(open_runs)):
            open_runs[run] = i
    done += [(first, len(keepout), *run) for run, first in open_runs.items()]
    return done


def split_holes(polygon: shapely.Polygon) -> list[shapely.Polygon]:
    """A polygon as hole-free polygons whose union is exactly it.

    Zones travel as vertex lists (scenario files, the zone topic, `ZoneSet.from_polygons`), which
    cannot carry holes. Cutting along a vertical line through a point inside a hole opens that
    hole into notches of the two halves, and leaves every other hole whole in one of them, so the
    recursion ends. The pieces touch along the cuts; `ZoneSet` merges them back into the polygon
    with its hole. Axis-aligned cuts of rectilinear (grid) polygons are exact in floating point.
    """
    if not polygon.interiors:
        return [polygon]
    x = shapely.Polygon(polygon.interiors[0]).point_on_surface().x
    x_min, y_min, x_max, y_max = polygon.bounds
    pieces = []
    for half in (shapely.box(x_min, y_min, x, y_max), shapely.box(x, y_min, x_max, y_max)):
        for part in shapely.get_parts(polygon.intersection(half)):
            if isinstance(part, shapely.Polygon) and part.area > 0:
                pieces += split_holes(part)
    return pieces


def grid_polygons(values: ArrayLike, resolution: float, origin: Sequence[float] = (0.0, 0.0),
                  threshold: int = DEFAULT_THRESHOLD, *, width: int | None = None,
                  height: int | None = None, workspace: Bounds | None = None,
                  caps: MaskCaps | None = None) -> list[np.ndarray]:
    """Vertices (V, 2), counter-clockwise, of hole-free polygons whose union is exactly the
    union of the keep-out cells (value >= threshold; -1 unknown is free), clipped to
    `workspace` if given. Empty if no cell is keep-out.

    Runs of cells become rectangles, shapely merges them, and collinear vertices are dropped.
    A region with a hole (a ring of cells) comes out as several pieces (`split_holes`), so every
    result is a simple polygon that `validate_polygon`, `ZoneSet.from_polygons`, the zone topic
    and the renderer take as it is. With `caps`, a mask that would cost more is refused
    (ValueError saying which cap) before the step that cap bounds.
    """
    if caps is not None and width is not None and height is not None \
            and width * height > caps.cells:
        raise ValueError(f"{width} x {height} cells, more than the {caps.cells} allowed")
    grid = _mask(values, width, height)
    res, ox, oy = _check_cells(resolution, origin)
    if not 0 < threshold <= 100:
        raise ValueError(f"threshold must be in (0, 100], got {threshold}")
    if caps is not None and grid.size > caps.cells:
        raise ValueError(f"{grid.size} cells, more than the {caps.cells} allowed")
    keepout = grid >= threshold
    if workspace is not None:  # cells wholly outside the workspace cost nothing to refuse
        keepout = keepout & _cells_meeting(grid.shape, res, ox, oy, workspace)
    rectangles = _rectangles(keepout)
    if caps is not None and len(rectangles) > caps.rectangles:
        raise ValueError(f"{len(rectangles)} rectangles of keep-out cells, more than the "
                         f"{caps.rectangles} allowed (a finer pattern than the node can hold)")
    boxes = [shapely.box(ox + c0 * res, oy + r0 * res, ox + c1 * res, oy + r1 * res)
             for r0, r1, c0, c1 in rectangles]
    union = shapely.union_all(boxes)
    if workspace is not None:
        union = union.intersection(shapely.box(*workspace))
    union = shapely.simplify(union, 0.0)
    parts = [p for p in shapely.get_parts(union) if isinstance(p, shapely.Polygon) and p.area > 0]
    pieces = [piece for part in parts for piece in split_holes(part)]
    if caps is not None:
        vertices = sum(len(p.exterior.coords) - 1 for p in pieces)
        if len(pieces) > caps.pieces or vertices > caps.vertices:
            raise ValueError(f"{len(pieces)} pieces of {vertices} vertices in all, more than "
                             f"the {caps.pieces} pieces or {caps.vertices} vertices allowed")
    return [np.asarray(shapely.orient_polygons(p, exterior_cw=False).exterior.coords)[:-1]
            for p in pieces]


def _cells_meeting(shape: tuple[int, int], res: float, ox: float, oy: float,
                   workspace: Bounds) -> np.ndarray:
    """(H, W) True for the cells that overlap the workspace with some area."""
    x_min, y_min, x_max, y_max = workspace
    rows, cols = np.arange(shape[0]), np.arange(shape[1])
    cols_in = (ox + cols * res < x_max) & (ox + (cols + 1) * res > x_min)
    rows_in = (oy + rows * res < y_max) & (oy + (rows + 1) * res > y_min)
    return rows_in[:, None] & cols_in[None, :]


def rasterize(polygons: Iterable[ArrayLike | shapely.Geometry], resolution: float,
              origin: Sequence[float], width: int, height: int) -> np.ndarray:
    """An OccupancyGrid mask (height, width) of int8: 100 where a cell's centre lies inside the
    union of `polygons` (vertex arrays or shapely geometries) or on its boundary, 0 elsewhere.

    Centres rather than covered area: an area rule (at least half inside) drops a convex corner
    cell covered less than half in both directions, which notches every corner of a square not
    aligned with the cells; by centres, a boundary moves by at most half a cell (half a diagonal
    at a corner) on the way to the grid and back (`grid_polygons`), either way. Grow the
    polygons by half a cell's diagonal first for a mask that covers them entirely.
    """
    res, ox, oy = _check_cells(resolution, origin)
    if width < 0 or height < 0:
        raise ValueError(f"grid size must be >= 0, got {width} x {height}")
    shapes = [p if isinstance(p, shapely.Geometry) else validate_polygon(p, f"polygon {i}")
              for i, p in enumerate(polygons)]
    grid = np.zeros((height, width), dtype=np.int8)
    union = shapely.union_all(shapes)
    if union.is_empty or grid.size == 0:
        return grid
    x_min, y_min, x_max, y_max = union.bounds  # only the cells whose centres could be inside
    c0, c1 = max(0, int((x_min - ox) // res)), min(width, int((x_max - ox) // res) + 1)
    r0, r1 = max(0, int((y_min - oy) // res)), min(height, int((y_max - oy) // res) + 1)
    if c0 >= c1 or r0 >= r1:
        return grid
    cols, rows = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
    shapely.prepare(union)
    inside = shapely.covers(union, shapely.points(ox + (cols + 0.5) * res,
                                                  oy + (rows + 0.5) * res))
    grid[r0:r1, c0:c1] = np.where(inside, KEEPOUT, 0)
    return grid


def read_pgm(path: str | Path, negate: bool = False) -> np.ndarray:
    """A binary PGM (P5) map image as OccupancyGrid values (H, W) int8, image row 0 first.

    As map_server reads a map (negate 0): the darker a pixel, the more occupied, value =
    round(100 (maxval - pixel) / maxval), so black is 100 and white 0 (`negate` swaps them).
    Rows are not flipped: the workspace frame has y down, like the image, where map_server's
    map frame has y up.
    """
    data = Path(path).read_bytes()
    fields, position = [], 0
    while len(fields) < 4:
        while position < len(data) and data[position:position + 1].isspace():
            position += 1
        if data[position:position + 1] == b"#":
            position = data.find(b"\n", position)
            position = len(data) if position < 0 else position
            continue
        end = position
        while end < len(data) and not data[end:end + 1].isspace():
            end += 1
        if end == position:
            raise ValueError(f"{path}: truncated PGM header")
        fields.append(data[position:end])
        position = end
    if fields[0] != b"P5":
        raise ValueError(f"{path}: not a binary PGM (P5), starts with {fields[0][:8]!r}")
    try:
        width, height, maxval = (int(f) for f in fields[1:])
    except ValueError:
        raise ValueError(f"{path}: malformed PGM header {fields!r}") from None
    if width < 1 or height < 1 or not 0 < maxval < 65536:
        raise ValueError(f"{path}: bad PGM size {width} x {height} or maxval {maxval}")
    if position >= len(data):
        raise ValueError(f"{path}: PGM header without pixels")
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    pixels = np.frombuffer(data, dtype=dtype, count=-1, offset=position + 1)
    if pixels.size < width * height:
        raise ValueError(f"{path}: {pixels.size} pixels for a {width} x {height} image")
    pixels = pixels[: width * height].reshape(height, width).astype(np.float64)
    darkness = pixels / maxval if negate else (maxval - pixels) / maxval
    return np.rint(100 * darkness).astype(np.int8)


@dataclass(frozen=True)
class BuiltMask:
    """A keep-out mask built by `MaskBuilder`: its pieces, or why it was refused."""

    sequence: int  # which `submit` it answers
    polygons: list[np.ndarray] | None  # None: refused
    reason: str = ""
    stamp: float | None = None  # the mask message's stamp, passed through
    seconds: float = 0.0  # how long the build took


def build_mask(grid: dict, caps: MaskCaps, workspace: Bounds | None, sequence: int = 0,
               stamp: float | None = None) -> BuiltMask:
    """`grid_polygons(**grid)` under `caps`, timed; any fault becomes the refusal's reason."""
    started = time.perf_counter()
    try:
        polygons = grid_polygons(**grid, workspace=workspace, caps=caps)
        built = BuiltMask(sequence, polygons, stamp=stamp)
    except ValueError as error:
        built = BuiltMask(sequence, None, " ".join(str(error).split()), stamp)
    except Exception as error:  # a mask must never end the builder's thread
        built = BuiltMask(sequence, None, f"{type(error).__name__}: {error}", stamp)
    return replace(built, seconds=time.perf_counter() - started)
