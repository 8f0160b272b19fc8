"""Keep-out grids: OccupancyGrid masks to exact polygons and back, and map images."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from constrained_diffusion_ros.evaluation.scenarios import load_scenarios
from constrained_diffusion_ros.runtime.mask_builder import MaskBuilder
from constrained_diffusion_ros.zones import ZoneSet, rectangle, validate_polygon
from constrained_diffusion_ros.zones.grid import (
    BuiltMask,
    MaskCaps,
    grid_polygons,
    rasterize,
    read_pgm,
)

WORKSPACE = (0.0, 0.0, 512.0, 512.0)


def union(polygons: list[np.ndarray]) -> shapely.Geometry:
    return shapely.union_all([shapely.Polygon(p) for p in polygons])


def test_the_center_square_round_trips_through_a_2px_mask_within_one_cell() -> None:
    square = load_scenarios()["center_0.2"].polygons[0]  # [204.8, 307.2]^2
    mask = rasterize([square], resolution=2, origin=(0, 0), width=256, height=256)
    assert mask.dtype == np.int8 and mask.shape == (256, 256)
    assert set(np.unique(mask).tolist()) == {0, 100}
    polygons = grid_polygons(mask, resolution=2)
    assert len(polygons) == 1 and len(polygons[0]) == 4  # one square, no staircase vertices
    back = shapely.Polygon(polygons[0])
    assert back.hausdorff_distance(shapely.Polygon(square)) <= 2.0
    assert back.equals(shapely.box(204, 204, 308, 308))  # cells whose centres are inside


def test_rasterize_marks_the_cells_whose_centres_are_inside() -> None:
    # Cells of 10 px from (0, 0): the triangle covers the centre (5, 5) of cell (0, 0) but not
    # the centre (15, 5) of cell (0, 1), though it covers part of that cell too.
    triangle = [[0, 0], [19, 0], [0, 19]]
    mask = rasterize([triangle], resolution=10, origin=(0, 0), width=3, height=2)
    assert mask.tolist() == [[100, 0, 0], [0, 0, 0]]
    assert not rasterize([], 10, (0, 0), 3, 2).any()
    far = rasterize([rectangle(100, 100, 120, 120)], 10, (0, 0), 3, 2)  # beyond the grid
    assert not far.any()


def test_thresholds_decide_keep_out_and_unknown_is_free() -> None:
    values = np.array([[-1, 0, 64, 65, 100]], dtype=np.int8)
    kept = union(grid_polygons(values, resolution=1))
    assert kept.equals(shapely.box(3, 0, 5, 1))  # 65 and 100: at least nav2's 0.65
    assert union(grid_polygons(values, 1, threshold=50)).equals(shapely.box(2, 0, 5, 1))
    assert union(grid_polygons(values, 1, threshold=100)).equals(shapely.box(4, 0, 5, 1))
    assert grid_polygons(np.full((4, 4), -1), 1) == []  # all unknown: nothing kept out
    for bad in (np.array([[0, 101]]), np.array([[-2, 0]])):
        with pytest.raises(ValueError, match=r"\[-1, 100\]"):
            grid_polygons(bad, 1)
    with pytest.raises(ValueError, match="integers"):
        grid_polygons(np.array([[0.5, 100.0]]), 1)
    with pytest.raises(ValueError, match="threshold"):
        grid_polygons(values, 1, threshold=0)


def test_origin_and_resolution_place_each_cell() -> None:
    values = np.zeros((3, 4), dtype=np.int8)
    values[1, 2] = 100  # row 1 (y), column 2 (x)
    polygons = grid_polygons(values, resolution=3, origin=(10, 20))
    assert union(polygons).equals(shapely.box(16, 23, 19, 26))
    flat = grid_polygons(values.ravel().tolist(), 3, (10, 20), width=4, height=3)
    assert union(flat).equals(union(polygons))  # row-major, row 0 first
    with pytest.raises(ValueError, match="4 x 2"):
        grid_polygons(values.ravel(), 3, width=4, height=2)
    with pytest.raises(ValueError, match="resolution"):
        grid_polygons(values, 0)


def test_a_ring_of_cells_keeps_its_hole_as_simple_pieces() -> None:
    ring = np.zeros((5, 5), dtype=np.int8)
    ring[1:4, 1:4] = 100
    ring[2, 2] = 0  # the hole: x in [25, 35], y in [27, 37]
    pieces = grid_polygons(ring, resolution=10, origin=(5, 7))
    assert len(pieces) >= 2
    for i, piece in enumerate(pieces):
        assert not validate_polygon(piece, f"piece {i}").interiors  # each a simple polygon
    expected = shapely.box(15, 17, 45, 47).difference(shapely.box(25, 27, 35, 37))
    zones = ZoneSet.from_polygons(pieces)
    assert zones.geometry.equals(expected)  # the pieces merge back into the ring with its hole
    inside = zones.contains(torch.tensor([[30.0, 32.0], [20.0, 32.0], [40.0, 40.0]]))
    assert inside.tolist() == [False, True, True]
    assert float(zones.signed_distance(torch.tensor([30.0, 32.0]))) == pytest.approx(5.0)


def test_cells_touching_at_a_corner_are_separate_valid_polygons() -> None:
    pieces = grid_polygons(np.array([[100, 0], [0, 100]]), resolution=1)
    assert sorted(shapely.Polygon(p).bounds for p in pieces) == [(0, 0, 1, 1), (1, 1, 2, 2)]
    assert ZoneSet.from_polygons(pieces).area == pytest.approx(2.0)


def test_empty_grid_and_clipping_to_the_workspace() -> None:
    assert grid_polygons(np.zeros((0, 0), dtype=np.int8), 1) == []
    assert grid_polygons(np.zeros((8, 8), dtype=np.int8), 4) == []
    band = np.full((1, 4), 100, dtype=np.int8)  # x in [-20, 180] at 50 px per cell
    clipped = grid_polygons(band, 50, origin=(-20, 490), workspace=WORKSPACE)
    assert union(clipped).equals(shapely.box(0, 490, 180, 512))
    assert union(grid_polygons(band, 50, origin=(-20, 490))).equals(shapely.box(-20, 490, 180, 540))
    assert grid_polygons(band, 50, origin=(600, 600), workspace=WORKSPACE) == []


def test_read_pgm_as_map_server_reads_it(tmp_path: Path) -> None:
    pixels = np.array([[0, 255, 254], [128, 77, 0]], dtype=np.uint8)  # black = occupied
    path = tmp_path / "mask.pgm"
    path.write_bytes(b"P5\n# saved by hand\n3 2\n255\n" + pixels.tobytes())
    values = read_pgm(path)
    assert values.dtype == np.int8
    assert values.tolist() == [[100, 0, 0], [50, 70, 100]]  # image row 0 is grid row 0
    assert read_pgm(path, negate=True).tolist() == [[0, 100, 100], [50, 30, 0]]
    polygons = grid_polygons(values, resolution=4)
    assert union(polygons).equals(shapely.union_all([shapely.box(0, 0, 4, 4),
                                                     shapely.box(4, 4, 12, 8)]))
    (tmp_path / "ascii.pgm").write_bytes(b"P2\n3 2\n255\n0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="P5"):
        read_pgm(tmp_path / "ascii.pgm")
    (tmp_path / "short.pgm").write_bytes(b"P5\n3 2\n255\n" + bytes(4))
    with pytest.raises(ValueError, match="4 pixels"):
        read_pgm(tmp_path / "short.pgm")


# -- what a mask may cost --------------------------------------------------------------------

def checkerboard(cells: int) -> np.ndarray:
    return (np.add.outer(np.arange(cells), np.arange(cells)) % 2 == 0).astype(np.int8) * 100


@pytest.mark.parametrize("mask, caps, cap", [
    (checkerboard(128), MaskCaps(), "rectangles"),  # 8,192 pieces: the node froze for minutes
    (np.zeros((5000, 5000), np.int8), MaskCaps(), "cells"),
    (checkerboard(16), MaskCaps(pieces=32), "pieces"),  # 128 pieces
    (np.kron(checkerboard(8)[:, :3], np.ones((1, 1), np.int8)), MaskCaps(vertices=64),
     "vertices"),  # 12 squares, 48 vertices; below
], ids=["rectangles", "cells", "pieces", "vertices"])
def test_a_mask_past_a_cap_is_refused_in_one_line_saying_which(mask, caps, cap) -> None:
    if cap == "vertices":  # under both caps first, then over the vertices cap
        assert len(grid_polygons(mask, 4.0, caps=caps)) == 12
        caps = MaskCaps(vertices=47)
    started = time.perf_counter()
    with pytest.raises(ValueError, match=cap) as refused:
        grid_polygons(mask, 4.0, workspace=WORKSPACE, caps=caps)
    assert "\n" not in str(refused.value)
    assert time.perf_counter() - started < 2.0  # refused before the union, not after


def test_cells_outside_the_workspace_cost_nothing() -> None:
    """A fine pattern wholly beyond the workspace is dropped before the caps count it."""
    mask = np.zeros((256, 256), np.int8)
    mask[:, 200:] = checkerboard(256)[:, 200:]  # x from 400 px: beyond 512 at 2 px cells
    mask[:, :200] = 0
    far = grid_polygons(mask, 4.0, origin=(0.0, 0.0), workspace=WORKSPACE,
                        caps=MaskCaps(rectangles=64))  # columns 200.. start at x = 800
    assert far == []


BUILD_BOUND_S = 2.0  # a mask up to the caps, on one core of the CI machine, with slack


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 256), st.integers(1, 256), st.floats(0.5, 8.0), st.integers(0, 2**32 - 1))
def test_random_masks_up_to_the_caps_are_built_or_refused_within_the_bound(
        width: int, height: int, resolution: float, seed: int) -> None:
    """Dense noise, blobs or stripes: built under the caps (or refused by one) in well under
    `BUILD_BOUND_S`, and what is built respects them."""
    rng = np.random.default_rng(seed)
    kind = seed % 3
    if kind == 0:
        mask = (rng.random((height, width)) < 0.5).astype(np.int8) * 100
    elif kind == 1:
        mask = np.zeros((height, width), np.int8)
        for _ in range(rng.integers(1, 40)):
            r, c = rng.integers(0, height), rng.integers(0, width)
            mask[r:r + rng.integers(1, 20), c:c + rng.integers(1, 20)] = 100
    else:
        mask = ((np.arange(width) // max(1, seed % 7)) % 2 == 0)[None].repeat(height, 0)
        mask = mask.astype(np.int8) * 100
    caps = MaskCaps()
    started = time.perf_counter()
    try:
        polygons = grid_polygons(mask, resolution, workspace=WORKSPACE, caps=caps)
    except ValueError as refused:
        assert any(cap in str(refused) for cap in ("rectangles", "pieces", "vertices"))
    else:
        assert len(polygons) <= caps.pieces
        assert sum(len(p) for p in polygons) <= caps.vertices
    assert time.perf_counter() - started < BUILD_BOUND_S


def test_the_mask_builder_builds_off_the_callers_thread_and_only_the_newest() -> None:
    """The caller returns at once; a mask superseded before it is built is never handed over."""
    built: list[BuiltMask] = []
    newest_in = threading.Event()
    threads: set[str] = set()
    last = 2  # the sequence number of the second submit

    def on_built(mask: BuiltMask) -> None:
        threads.add(threading.current_thread().name)
        built.append(mask)
        if mask.sequence == last:
            newest_in.set()

    builder = MaskBuilder(on_built, MaskCaps(), WORKSPACE)
    try:
        started = time.perf_counter()
        builder.submit(values=checkerboard(128), resolution=4.0)  # refused: too fine
        square = np.zeros((128, 128), np.int8)
        square[10:20, 10:20] = 100
        assert builder.submit(1.5, values=square, resolution=4.0) == last
        assert time.perf_counter() - started < 0.05  # nothing built on this thread
        assert newest_in.wait(10.0)
        newest = built[-1]
        assert newest.sequence == last and newest.stamp == 1.5 and newest.polygons is not None
        assert len(newest.polygons) == 1
        assert all(m.sequence == last or m.polygons is None for m in built)
        assert threads == {"mask_builder"}
    finally:
        builder.shutdown()
