"""Restricted-zone geometry checked against shapely, and the live zone set's bookkeeping."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from constrained_diffusion_ros.zones import RestrictedArea, ZoneSet, rectangle, validate_polygon
from constrained_diffusion_ros.zones.geometry import leaves_no_room

L_SHAPE = np.array([[100, 100], [300, 100], [300, 160], [160, 160], [160, 400], [100, 400]])


def star(rng: np.random.Generator, center: tuple[float, float], r_min: float, r_max: float):
    """Random star-shaped (generally concave) polygon: sorted angles, random radii."""
    angles = np.sort(rng.uniform(0, 2 * math.pi, rng.integers(5, 14)))
    radii = rng.uniform(r_min, r_max, len(angles))
    return np.stack([center[0] + radii * np.cos(angles), center[1] + radii * np.sin(angles)], 1)


def zone_cases() -> dict[str, list[np.ndarray]]:
    rng = np.random.default_rng(7)
    return {
        "star": [star(rng, (256, 256), 40, 200)],
        "star2": [star(rng, (200, 300), 20, 150)],
        "l_shape": [L_SHAPE],
        # Overlapping stars: union with notches and possibly holes.
        "star_union": [star(rng, (150 + 60 * i, 250), 30, 120) for i in range(4)],
        "overlap_rects": [rectangle(100, 100, 250, 200), rectangle(200, 150, 350, 350)],
        "adjacent_rects": [rectangle(100, 100, 200, 200), rectangle(200, 100, 300, 250)],
        "narrow_gap": [rectangle(50, 50, 200, 450), rectangle(210, 50, 400, 450), L_SHAPE + 100],
    }


CASES = zone_cases()


def random_points(n: int, seed: int = 0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).uniform(-20, 532, (n, 2)))


@pytest.mark.parametrize("name", list(CASES))
def test_contains_and_distance_match_shapely(name: str) -> None:
    zones = ZoneSet.from_polygons(CASES[name])
    union = shapely.union_all([shapely.Polygon(p) for p in CASES[name]])
    points = random_points(1000)
    x, y = points.numpy().T
    boundary_distance = shapely.distance(union.boundary, shapely.points(x, y))
    inside = shapely.contains_xy(union, x, y)
    clear = boundary_distance > 1e-6
    assert clear.sum() > 900 and 50 < inside.sum() < 950  # a real mix of inside and outside

    assert np.array_equal(zones.contains(points).numpy()[clear], inside[clear])
    signed = zones.signed_distance(points).numpy()
    np.testing.assert_allclose(np.abs(signed), boundary_distance, atol=1e-4)
    assert np.array_equal((signed < 0)[clear], inside[clear])
    assert zones.area == pytest.approx(union.area)


def test_overlapping_union_uses_union_boundary() -> None:
    zones = ZoneSet.from_polygons([rectangle(0, 0, 100, 100), rectangle(50, 0, 200, 100)])
    assert len(zones) == 1 and zones.area == pytest.approx(200 * 100)
    point = torch.tensor([75.0, 50.0])  # in the overlap, on both rectangles' inner edges' lines
    assert zones.contains(point)
    # 25 px from each original rectangle's edge, but 50 px from the union's boundary.
    assert zones.signed_distance(point).item() == pytest.approx(-50.0)


def test_outward_direction_hand_made() -> None:
    zones = ZoneSet.from_polygons([rectangle(0, 0, 100, 100)])
    points = torch.tensor([[5.0, 50.0], [50.0, 97.0], [-10.0, 50.0], [0.0, 50.0], [100.0, 30.0]])
    expected = torch.tensor([[-1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]])
    torch.testing.assert_close(zones.outward_direction(points), expected)

    union = ZoneSet.from_polygons(CASES["star_union"])
    norms = union.outward_direction(random_points(500)).norm(dim=-1)
    torch.testing.assert_close(norms, torch.ones_like(norms))

    corner = zones.outward_direction(torch.tensor([[100.0, 100.0]]))  # the exterior bisector
    torch.testing.assert_close(corner, torch.tensor([[0.5**0.5, 0.5**0.5]]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["star_union", "l_shape", "adjacent_rects", "narrow_gap"])
def test_outward_direction_of_a_point_does_not_depend_on_the_others(name: str) -> None:
    """A batch with a point on the boundary (a vertex, an edge) takes the boundary's rules for
    it; the points off it get the same directions as in a batch without one."""
    zones = ZoneSet.from_polygons(CASES[name])
    vertices = torch.as_tensor(np.concatenate(zones.polygons))
    on_edges = (vertices + vertices.roll(-1, dims=0)) / 2
    points = torch.cat([random_points(200), vertices, on_edges])
    each = torch.cat([zones.outward_direction(point[None]) for point in points])
    assert torch.equal(zones.outward_direction(points), each)
    assert torch.equal(zones.outward_direction(points[:200]), each[:200])


def test_queries_keep_batch_shape_and_dtype() -> None:
    zones = ZoneSet.from_polygons([L_SHAPE])
    assert isinstance(zones, RestrictedArea)
    points = random_points(3 * 4 * 16).reshape(3, 4, 16, 2).float()
    assert zones.contains(points).shape == (3, 4, 16)
    assert zones.signed_distance(points).dtype == torch.float32
    assert zones.outward_direction(points).shape == (3, 4, 16, 2)
    assert zones.project_out(points, 5.0).dtype == torch.float32
    fraction = zones.segment_clear_fraction(points[..., :-1, :], points[..., 1:, :])
    assert fraction.shape == (3, 4, 15) and fraction.dtype == torch.float32


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("margin", [0.0, 15.0])
@pytest.mark.parametrize("name", ["star_union", "l_shape", "adjacent_rects", "narrow_gap"])
def test_project_out_leaves_nothing_inside(name: str, margin: float, dtype: torch.dtype) -> None:
    zones = ZoneSet.from_polygons(CASES[name])
    points = random_points(1000, seed=1).to(dtype)
    before = zones.signed_distance(points.double())
    moved = zones.project_out(points, margin)

    assert moved.dtype == dtype
    assert (zones.signed_distance(moved.double()) >= margin - 1e-6).all()
    far = before >= margin
    assert (~far).sum() > 50 and torch.equal(moved[far], points[far])
    # Moved about as little as possible: the nearest clear point lies on the boundary of the
    # union grown by `margin` (finely approximated here); allow float32 rounding and arc sag.
    grown = shapely.union_all([shapely.Polygon(p) for p in CASES[name]])
    grown = grown.buffer(margin, quad_segs=256) if margin else grown
    near = (~far).numpy()
    x, y = points.double().numpy()[near].T
    shortest = shapely.distance(grown.boundary, shapely.points(x, y))
    travelled = (moved.double() - points.double()).norm(dim=-1).numpy()[near]
    assert (travelled <= shortest + 2e-3 * margin + 1e-2).all()


def test_project_out_escapes_a_gap_narrower_than_twice_the_margin() -> None:
    zones = ZoneSet.from_polygons([rectangle(0, 0, 100, 100), rectangle(110, 0, 200, 100)])
    moved = zones.project_out(torch.tensor([105.0, 90.0]), margin=15.0)
    # Clear of both top corners: 15 px from (100, 100) and (110, 100) at x = 105.
    torch.testing.assert_close(
        moved, torch.tensor([105.0, 100 + math.sqrt(15**2 - 5**2)]), atol=0.05, rtol=0
    )


def test_project_out_derives_the_grown_area_only_where_one_edge_does_not_decide() -> None:
    """A point one edge decides takes the one-step projection (as short as a move can be);
    only a gap narrower than twice the margin needs the candidates on the grown area."""
    zones = ZoneSet.from_polygons([rectangle(0, 0, 100, 100), rectangle(110, 0, 200, 100)])
    moved = zones.project_out(torch.tensor([[50.0, 90.0]]), margin=15.0)
    torch.testing.assert_close(moved, torch.tensor([[50.0, 115.0]]), atol=1e-3, rtol=0)
    assert ("fine", 15.0) not in zones.__dict__.get("_derived_areas", {})
    zones.project_out(torch.tensor([[105.0, 90.0]]), margin=15.0)
    assert ("fine", 15.0) in zones._derived_areas


def test_segment_clear_fraction_and_crosses() -> None:
    zones = ZoneSet.from_polygons([rectangle(100, 100, 200, 200)])
    starts = torch.tensor([[0.0, 150.0], [0.0, 50.0], [150.0, 150.0], [0.0, 150.0], [0.0, 100.0]])
    ends = torch.tensor(
        [[300.0, 150.0], [300.0, 50.0], [400.0, 150.0], [100.0, 150.0], [300.0, 100.0]]
    )
    # through it, misses it, starts inside, ends on the boundary, slides along an edge
    fraction = zones.segment_clear_fraction(starts, ends)
    torch.testing.assert_close(fraction, torch.tensor([1 / 3, 1.0, 0.0, 1.0, 1.0]))
    assert zones.crosses(starts, ends).tolist() == [True, False, True, False, False]
    # Through vertices: into a corner, grazing a corner, entering past the concave notch tip
    # (160, 160) straight or after sliding along an edge, grazing that tip.
    corners = torch.tensor([[[0.0, 0.0], [150.0, 150.0]], [[0.0, 200.0], [200.0, 0.0]]])
    fraction = zones.segment_clear_fraction(corners[:, 0], corners[:, 1])
    torch.testing.assert_close(fraction, torch.tensor([2 / 3, 1.0]))
    l_shape = ZoneSet.from_polygons([L_SHAPE])
    segments = torch.tensor(
        [
            [[200.0, 300.0], [200.0, 50.0]],
            [[220.0, 220.0], [100.0, 100.0]],
            [[250.0, 160.0], [100.0, 160.0]],
            [[200.0, 200.0], [140.0, 140.0]],
            [[220.0, 200.0], [120.0, 100.0]],
        ]
    )
    fraction = l_shape.segment_clear_fraction(segments[:, 0], segments[:, 1])
    torch.testing.assert_close(fraction, torch.tensor([140 / 250, 0.5, 0.6, 2 / 3, 0.4]))
    tangent = torch.tensor([[[160.0, 240.0], [160.0, 170.0]], [[400.0, 160.0], [170.0, 160.0]]])
    assert not l_shape.crosses(tangent[:, 0], tangent[:, 1]).any()


@pytest.mark.parametrize(
    ("vertices", "fault"),
    [
        ([[0, 0], [1, 1]], "at least 3 distinct"),
        ([[0, 0], [0, 0], [1, 1], [1, 1]], "at least 3 distinct"),
        ([[0, 0], [1, math.nan], [1, 1]], "finite"),
        ([[0, 0], [1, 1], [2, 2], [3, 3]], "collinear"),
        ([[0, 0], [1, 1], [1, 0], [0, 1]], "Self-intersection"),
    ],
)
def test_degenerate_polygons_refused(vertices: list, fault: str) -> None:
    with pytest.raises(ValueError, match=f"polygon 1: .*{fault}"):
        ZoneSet.from_polygons([rectangle(0, 0, 10, 10), vertices])


def test_inflate_keeps_a_disc_out() -> None:
    inflated = ZoneSet.from_polygons([rectangle(100, 100, 200, 200)]).inflate(15.0)
    assert inflated.contains(torch.tensor([[210.0, 150.0], [150.0, 90.0]])).all()
    assert not inflated.contains(torch.tensor([[220.0, 150.0], [150.0, 80.0]])).any()
    # Round joins: a corner's diagonal clearance is 15, not 15 * sqrt(2).
    assert inflated.signed_distance(torch.tensor([212.0, 212.0])).item() > 0


def test_empty_set_restricts_nothing() -> None:
    zones = ZoneSet.empty()
    points = random_points(10)
    assert zones.is_empty and len(zones) == 0 and zones.polygons == []
    assert not zones.contains(points).any()
    assert torch.isinf(zones.signed_distance(points)).all()
    assert torch.equal(zones.project_out(points, 15.0), points)
    assert (zones.segment_clear_fraction(points, points.flip(0)) == 1).all()


def test_near_answers_like_the_whole_set_for_points_close_by() -> None:
    """The shield checks hundreds of path points near one pusher: `near` drops the far rings
    and must not change an answer that matters (inside, or a distance below the reach)."""
    squares = [rectangle(x, y, x + 20, y + 20) for x in range(0, 500, 60)
               for y in range(0, 500, 60)]  # 81 zones, apart even when inflated
    zones = ZoneSet.from_polygons(squares).inflate(15.0)
    points = 100 + 80 * torch.rand(500, 2, generator=torch.Generator().manual_seed(0),
                                   dtype=torch.float64)
    view = zones.near(points, 5.0)
    assert repr(view) != repr(zones)  # fewer edges
    assert torch.equal(view.contains(points), zones.contains(points))
    whole, local = zones.signed_distance(points), view.signed_distance(points)
    close = whole < 5.0
    assert close.any() and torch.equal(local[close], whole[close])
    assert (local[~close] >= 5.0).all()
    # What moves points answers for the whole set: no point lands in a dropped ring.
    assert torch.equal(view.project_out(points, 5.0), zones.project_out(points, 5.0))


@pytest.mark.parametrize("enclosing", ["workspace frame", "zone with a hole"])
def test_near_drops_a_ring_around_the_points_and_still_knows_they_are_inside_it(
        enclosing: str) -> None:
    """A ring far from every point but around them (the workspace frame's outer ring around
    the workspace; a zone's outer ring around points by its hole) leaves the view, and the
    points stay inside (or outside) it as in the whole set."""
    if enclosing == "workspace frame":
        zones = ZoneSet.from_polygons([rectangle(200, 200, 240, 240)]).bounded(
            (0.0, 0.0, 512.0, 512.0)).inflate(15.0)
    else:
        zones = ZoneSet([shapely.box(0, 0, 400, 400).difference(shapely.box(180, 180, 220, 220))])
    points = 150 + 100 * torch.rand(500, 2, generator=torch.Generator().manual_seed(1),
                                    dtype=torch.float64)
    view = zones.near(points, 5.0)
    assert len(view._table) < len(zones._table)  # the far ring is gone
    inside = zones.contains(points)
    assert inside.any() and (~inside).any() and torch.equal(view.contains(points), inside)
    whole, local = zones.signed_distance(points), view.signed_distance(points)
    close = whole.abs() < 5.0
    assert close.any() and torch.equal(local[close], whole[close])
    assert torch.equal(local < 5.0, whole < 5.0)


def test_leaves_no_room_counts_every_piece_grown() -> None:
    """Many small pieces grown by r cover more than one piece's bound (k pi r^2, not pi r^2):
    625 cells of 2 px, 21 px apart, grown by 15 px cover the 512 px workspace; 16 px apart with
    a 40 px gap in the middle of the grid they do not."""
    cells = shapely.union_all([shapely.box(x, y, x + 2, y + 2) for x in range(0, 525, 21)
                               for y in range(0, 525, 21)])
    assert leaves_no_room(cells, (0.0, 0.0, 512.0, 512.0), 15.0)
    gap = shapely.box(236, 236, 276, 276).buffer(15.0)
    assert not leaves_no_room(cells.difference(gap), (0.0, 0.0, 512.0, 512.0), 15.0)
    assert leaves_no_room(shapely.box(-10, -10, 600, 600), (0.0, 0.0, 512.0, 512.0), 0.0)
    assert not leaves_no_room(shapely.box(0, 0, 100, 100), (0.0, 0.0, 512.0, 512.0), 15.0)


def test_a_zone_with_a_far_vertex_is_clipped_then_judged_not_called_collinear() -> None:
    """A vertex at 1e30 swamped a rank test, and a zone with 32,400 px^2 in the workspace was
    refused as "all vertices are collinear"; clipped first, it is accepted as that part."""
    zone = validate_polygon([[300, 200], [1e30, 250], [400, 400]], "zone", (0, 0, 512, 512))
    assert zone.area == pytest.approx(32400.0)
