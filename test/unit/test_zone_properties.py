"""Property-based tests (hypothesis) of what the zone validator and the live zone set accept:
every accepted zone is enforced, every refused one leaves the zones in force unchanged.

Polygons are drawn the way messages bring them: float32 coordinates (`Point32`), from the
workspace to far beyond it (up to 1e30), collinear runs that round to slivers, repeated points,
self-intersections."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import shapely
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.geometry import ZoneSet, validate_polygon
from constrained_diffusion_ros.zones.live import LiveZones

WORKSPACE = PUSHT_ROBOT.workspace
RADIUS = PUSHT_ROBOT.pusher_radius
SETTINGS = settings(max_examples=1500, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])

coordinate = st.one_of(
    st.floats(-100, 612), st.floats(-1e30, 1e30), st.sampled_from([0.0, 256.0, 512.0, 1e18]))
point = st.tuples(coordinate, coordinate)


@st.composite
def message_polygons(draw) -> np.ndarray:
    """Vertices as a Point32 message carries them: float32, 0 to 12 of them."""
    kind = draw(st.sampled_from(["free", "free", "collinear", "box"]))
    if kind == "free":
        vertices = draw(st.lists(point, min_size=0, max_size=12))
    elif kind == "collinear":  # a line, nudged off it by at most float32 rounding
        start, end = draw(point), draw(point)
        t = draw(st.lists(st.floats(0, 1), min_size=3, max_size=8))
        vertices = [(start[0] + s * (end[0] - start[0]), start[1] + s * (end[1] - start[1]))
                    for s in t]
    else:
        x0, y0, x1, y1 = (draw(coordinate) for _ in range(4))
        vertices = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return np.asarray(vertices, dtype=np.float32).reshape(-1, 2).astype(np.float64)


def probe_points(polygon) -> torch.Tensor:
    """Points of the zone and around it: a grid over its bounds grown by the radius, plus a
    point surely inside."""
    x_min, y_min, x_max, y_max = polygon.bounds
    xs = np.linspace(x_min - RADIUS, x_max + RADIUS, 12)
    ys = np.linspace(y_min - RADIUS, y_max + RADIUS, 12)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    inside = np.asarray(polygon.representative_point().coords)
    return torch.from_numpy(np.concatenate([grid, inside]))


@SETTINGS
@given(message_polygons())
def test_an_accepted_zone_is_enforced_once_inflated(vertices: np.ndarray) -> None:
    try:
        polygon = validate_polygon(vertices, "zone", WORKSPACE)
    except ValueError:
        return  # refused: nothing to enforce (the live-set test checks nothing changed)
    x_min, y_min, x_max, y_max = polygon.bounds
    assert WORKSPACE[0] <= x_min and x_max <= WORKSPACE[2]  # clipped to the workspace
    assert WORKSPACE[1] <= y_min and y_max <= WORKSPACE[3]
    area = ZoneSet([polygon]).inflate(RADIUS)
    points = probe_points(polygon)
    assert area.contains(points).any()  # not empty after inflation: it keeps something out
    moved = area.project_out(points)
    assert not area.contains(moved).any()


ids = st.integers(0, 5)
message = st.tuples(ids, st.one_of(message_polygons(), st.just(np.zeros((0, 2)))))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(message, min_size=1, max_size=20))
def test_a_refused_message_leaves_the_zones_in_force_unchanged(messages) -> None:
    """Messages one at a time into a set capped at 4 zones of 8 vertices: an accepted one is
    in force exactly as validated, a refused one changes nothing, the caps always hold."""
    live = LiveZones(max_zones=4, max_vertices=8, workspace=WORKSPACE)
    for zone_id, vertices in messages:
        before = {i: v.copy() for i, v in live.outlines().items()}
        version = live.version
        outcome = live.apply([(zone_id, vertices)], now=0.0)
        if outcome.refused:
            assert live.version == version
            after = live.outlines()
            assert after.keys() == before.keys()
            assert all(np.array_equal(after[i], before[i]) for i in before)
        elif len(vertices) == 0:
            assert zone_id not in live.ids
        else:
            assert zone_id in live.ids
            expected = validate_polygon(vertices, "zone", WORKSPACE)
            assert live.snapshot().geometry.contains(expected.representative_point())
        assert len(live.ids) <= 4
    snapshot = live.snapshot()
    if not snapshot.is_empty:  # whatever was accepted, the union is enforced
        points = probe_points(snapshot.geometry)
        area = snapshot.inflate(RADIUS)
        assert not area.contains(area.project_out(points)).any()


def test_the_reported_cases_are_clipped_or_refused() -> None:
    """The issue's square from -1e30 to 1e30 is the workspace, enforced; collinear points that
    float32 rounding bends into a sliver are refused."""
    everything = np.asarray([(-1e30, -1e30), (1e30, -1e30), (1e30, 1e30), (-1e30, 1e30)],
                            dtype=np.float32).astype(np.float64)
    polygon = validate_polygon(everything, "zone", WORKSPACE)
    assert polygon.area == pytest.approx((WORKSPACE[2] - WORKSPACE[0])
                                         * (WORKSPACE[3] - WORKSPACE[1]))
    sliver = np.asarray([(0, 0), (256, 256.00001), (512, 512)],
                        dtype=np.float32).astype(np.float64)
    with pytest.raises(ValueError, match=r"collinear|sliver|area"):
        validate_polygon(sliver, "zone", WORKSPACE)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(message_polygons(), min_size=0, max_size=3),
       st.tuples(st.floats(0, 512), st.floats(0, 512)), st.floats(0.5, 80),
       st.floats(0, 20), st.integers(0, 2**16), st.floats(2, 60))
def test_near_answers_like_the_whole_area_the_shield_sees(polygons, centre, spread, reach,
                                                          seed, side) -> None:
    """The shield asks `near(path points, margin)` of the zones bounded by the workspace and
    inflated: the same inside test, and the same distance wherever it is below the reach.
    A square of `side` px beside the points' centre, and messages' polygons."""
    x, y = centre
    accepted = [shapely.box(x + side / 4, y, x + side, y + side)]
    for vertices in polygons:
        with contextlib.suppress(ValueError):  # refused zones are not in force
            accepted.append(validate_polygon(vertices, "zone", WORKSPACE))
    area = ZoneSet(accepted).bounded(WORKSPACE).inflate(RADIUS)
    generator = torch.Generator().manual_seed(seed)
    points = torch.tensor(centre) + spread * (torch.rand(120, 2, generator=generator) - 0.5)
    view = area.near(points, reach)
    assert torch.equal(view.contains(points), area.contains(points))
    whole, local = area.signed_distance(points), view.signed_distance(points)
    close = whole.abs() < reach
    assert torch.equal(local[close], whole[close])
    assert torch.equal(local < reach, whole < reach)
