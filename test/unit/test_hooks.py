"""The constraint hooks on hand-made samples: resampling, gradient push, projection, path repair."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st
from samples import CENTRE, L_SHAPE, LEFT_BAND, NORMALIZER, OVERLAPPING, SQUARE, make_step

from constrained_diffusion_ros.sampling.hooks import (
    FinalProjection,
    GradientPush,
    PathRepair,
    Resampling,
    ResamplingThenPush,
    ShrinkingMargin,
    Until,
)
from constrained_diffusion_ros.zones import ZoneSet, rectangle

# -- Resampling ----------------------------------------------------------------------------------

# Two episodes of four waypoints; those at x in (100, 200) and y in (100, 200) are inside SQUARE.
HAND_MADE = torch.tensor([[[150.0, 150.0], [20.0, 30.0], [199.0, 101.0], [400.0, 150.0]],
                          [[300.0, 300.0], [120.0, 180.0], [250.0, 90.0], [101.0, 199.0]]])
HAND_MADE_INSIDE = torch.tensor([[True, False, True, False], [False, True, False, True]])


def test_hand_made_sample_has_the_expected_inside_waypoints() -> None:
    assert torch.equal(SQUARE.contains(HAND_MADE), HAND_MADE_INSIDE)


def test_resampling_replaces_inside_waypoints_by_the_fresh_draw_at_the_first_step() -> None:
    step = make_step(0)
    assert step.progress == 0.0
    out = Resampling(SQUARE)(HAND_MADE.clone(), step)
    fresh = NORMALIZER.unnormalize(
        torch.randn(HAND_MADE.shape, generator=torch.Generator().manual_seed(7)))
    inside = HAND_MADE_INSIDE
    assert torch.equal(out[inside], fresh[inside])
    assert torch.equal(out[~inside], HAND_MADE[~inside])
    # The draw is centred on the action space: N(0, 1) normalised is 256 +- 256 px here.
    assert not torch.equal(out[inside], HAND_MADE[inside])


def test_resampling_leaves_the_sample_unchanged_at_the_last_step() -> None:
    step = make_step(4)
    assert step.progress == 1.0
    out = Resampling(SQUARE)(HAND_MADE.clone(), step)
    assert torch.equal(out, HAND_MADE)


def test_resampling_blends_linearly_in_between() -> None:
    out = Resampling(SQUARE)(HAND_MADE.clone(), make_step(1, total=5))  # progress 1/4: w = 3/4
    fresh = NORMALIZER.unnormalize(
        torch.randn(HAND_MADE.shape, generator=torch.Generator().manual_seed(7)))
    expected = 0.75 * fresh + 0.25 * HAND_MADE
    inside = HAND_MADE_INSIDE
    torch.testing.assert_close(out[inside], expected[inside])
    assert torch.equal(out[~inside], HAND_MADE[~inside])


def test_resampling_draws_nothing_when_no_waypoint_is_inside() -> None:
    outside = HAND_MADE[:, :2][~HAND_MADE_INSIDE[:, :2]].reshape(2, 1, 2)  # one per episode
    assert not SQUARE.contains(outside).any()
    step = make_step(0)
    out = Resampling(SQUARE)(outside, step)
    assert torch.equal(out, outside)
    # The generator was not advanced: its next draw is its first.
    assert torch.equal(torch.randn(3, generator=step.generator),
                       torch.randn(3, generator=torch.Generator().manual_seed(7)))


# -- Gradient push -------------------------------------------------------------------------------

def test_gradient_push_moves_inside_points_lambda_toward_the_nearest_edge() -> None:
    points = torch.tensor([[[105.0, 150.0], [150.0, 196.0], [50.0, 150.0], [205.0, 150.0]]])
    out = GradientPush(SQUARE, 3.0)(points.clone(), make_step(2))
    torch.testing.assert_close(out[0, 0] - points[0, 0], torch.tensor([-3.0, 0.0]))
    torch.testing.assert_close(out[0, 1] - points[0, 1], torch.tensor([0.0, 3.0]))
    assert torch.equal(out[0, 2:], points[0, 2:])  # outside: untouched


def test_gradient_push_in_a_concave_zone_heads_for_the_nearest_boundary() -> None:
    points = torch.tensor([[190.0, 190.0],  # nearest boundary: the notch vertex (200, 200)
                           [250.0, 180.0],  # horizontal arm, nearest its lower edge y = 200
                           [170.0, 300.0]])  # vertical arm, nearest its left edge x = 150
    assert L_SHAPE.contains(points).all()
    step_size = 4.0
    out = GradientPush(L_SHAPE, step_size)(points.clone(), make_step(0))
    diagonal = 1 / math.sqrt(2)
    expected = torch.tensor([[diagonal, diagonal], [0.0, 1.0], [-1.0, 0.0]]) * step_size
    torch.testing.assert_close(out - points, expected)
    # A push that heads for the centroid of the L (about (208, 213)) would go the other way.
    assert (out[0] - points[0] > 0).all()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), index=st.integers(0, 4), spread=st.floats(20.0, 300.0))
def test_resampling_then_push_is_the_two_hooks_in_turn_bit_for_bit(seed: int, index: int,
                                                                   spread: float) -> None:
    """The fused hook the planner uses where a configuration has both gives exactly what the
    two give in turn, the same noise drawn, whether or not a waypoint is inside."""
    generator = torch.Generator().manual_seed(seed)
    sample = 150.0 + spread * (torch.rand(2, 6, 2, generator=generator) - 0.5)
    for area in (SQUARE, L_SHAPE):
        step = make_step(index, seed=seed)  # one generator for both, as the sampler passes it
        apart = GradientPush(area, 10.0)(Resampling(area)(sample.clone(), step), step)
        together = ResamplingThenPush(area, 10.0)(sample.clone(), make_step(index, seed=seed))
        assert torch.equal(apart, together)


def test_inside_and_outward_is_contains_and_outward_direction() -> None:
    """A zone set answers both in one query; its answer is the two queries'."""
    points = torch.tensor([[[105.0, 150.0], [150.0, 196.0], [50.0, 150.0], [250.0, 180.0]]])
    for area in (SQUARE, L_SHAPE):
        inside, outward = area.inside_and_outward(points)
        assert torch.equal(inside, area.contains(points))
        assert torch.equal(outward, area.outward_direction(points))
    inside, outward = SQUARE.inside_and_outward(torch.tensor([[50.0, 50.0]]))
    assert not inside.any() and outward is None  # nothing inside: no directions computed


# -- Final projection ----------------------------------------------------------------------------

def test_final_projection_acts_only_at_the_last_step() -> None:
    hook = FinalProjection(SQUARE, margin=2.0)
    for index in range(4):
        assert torch.equal(hook(HAND_MADE.clone(), make_step(index)), HAND_MADE)
    out = hook(HAND_MADE.clone(), make_step(4))
    assert not SQUARE.contains(out).any()
    assert torch.equal(out[~HAND_MADE_INSIDE], HAND_MADE[~HAND_MADE_INSIDE])


@pytest.mark.parametrize("margin", [0.0, 1.0, 5.0])
@pytest.mark.parametrize("area", [SQUARE, L_SHAPE, OVERLAPPING, LEFT_BAND, CENTRE],
                         ids=["square", "l_shape", "overlapping", "left_band", "centre"])
def test_final_projection_leaves_no_waypoint_inside_or_closer_than_the_margin(
        area: ZoneSet, margin: float) -> None:
    generator = torch.Generator().manual_seed(3)
    sample = torch.rand(64, 16, 2, generator=generator) * 512
    assert area.contains(sample).any()  # otherwise the test proves nothing
    out = FinalProjection(area, margin)(sample.clone(), make_step(9, total=10))
    assert not area.contains(out).any()
    assert area.signed_distance(out).min() >= margin - 1e-4
    far = area.signed_distance(sample) >= margin
    assert torch.equal(out[far], sample[far])


# -- Path repair ---------------------------------------------------------------------------------

def path_segments(start: torch.Tensor, path: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Segments start -> path[0] -> path[1] -> ... per episode."""
    return torch.cat([start[:, None], path[:, :-1]], dim=1), path


def test_path_repair_from_a_progress_repairs_after_every_update_from_it_on() -> None:
    zone = ZoneSet.from_polygons([rectangle(200, 200, 300, 300)])
    start = torch.tensor([[100.0, 250.0]])
    xs = torch.linspace(140.0, 460.0, 8)
    sample = torch.stack([xs, torch.full_like(xs, 250.0)], dim=-1)[None]  # straight through
    hook = PathRepair(zone, start, first_index=0, margin=1.0, from_progress=0.5)
    assert torch.equal(hook(sample.clone(), make_step(1)), sample)  # progress 0.25: not yet
    for index in (2, 3):  # progress 0.5 and 0.75: repaired already
        out = hook(sample.clone(), make_step(index))
        assert not zone.crosses(*path_segments(start, out)).any()


def test_shrinking_margin_guides_on_a_grown_area_first_and_the_area_itself_last() -> None:
    near = torch.tensor([[[95.0, 150.0], [300.0, 300.0]]])  # 5 px left of SQUARE; far away
    hook = ShrinkingMargin(GradientPush(SQUARE, 1.0), extra=10.0)
    first = hook(near.clone(), make_step(0))
    assert first[0, 0, 0] < 95.0 and torch.equal(first[0, 1], near[0, 1])  # pushed further out
    assert torch.equal(hook(near.clone(), make_step(4)), near)  # last update: SQUARE itself
    assert hook.hook.area is SQUARE  # the hook it wraps is left as it was


def test_until_runs_its_hook_only_up_to_the_progress_given() -> None:
    hook = Until(GradientPush(SQUARE, 10.0), last=0.5)
    moved = [not torch.equal(hook(HAND_MADE.clone(), make_step(i)), HAND_MADE)
             for i in range(5)]
    assert moved == [True, True, True, False, False]


def test_path_repair_pulls_a_crossing_path_back_before_the_zone() -> None:
    zone = ZoneSet.from_polygons([rectangle(200, 200, 300, 300)])
    start = torch.tensor([[100.0, 250.0], [100.0, 100.0]])
    xs = torch.linspace(140.0, 460.0, 8)
    crossing = torch.stack([xs, torch.full_like(xs, 250.0)], dim=-1)  # straight through it
    clear = torch.stack([xs, torch.full_like(xs, 100.0)], dim=-1)  # parallel, above it
    head = torch.tensor([[[250.0, 250.0]], [[250.0, 250.0]]])  # not executed: left alone
    sample = torch.cat([head, torch.stack([crossing, clear])], dim=1)  # (2, 9, 2)
    first_starts, first_ends = path_segments(start, sample[:, 1:])
    assert zone.crosses(first_starts, first_ends)[0].any()
    assert not zone.crosses(first_starts, first_ends)[1].any()

    hook = PathRepair(zone, start, first_index=1, margin=1.0, slide=False)
    assert torch.equal(hook(sample.clone(), make_step(0)), sample)  # only after the last update
    out = hook(sample.clone(), make_step(4))

    assert torch.equal(out[:, :1], sample[:, :1])
    assert torch.equal(out[1], sample[1])  # the clear path is unchanged
    starts, ends = path_segments(start, out[:, 1:])
    assert not zone.crosses(starts, ends).any()
    assert not zone.contains(out[0, 1:]).any()
    # Waypoints before the crossing stay; the rest stop just short of the entry at x = 200.
    before = xs < 200
    assert torch.equal(out[0, 1:][before], crossing[before])
    torch.testing.assert_close(out[0, 1:][~before][:, 0],
                               torch.full((int((~before).sum()),), 199.0), atol=1e-3, rtol=0)




def test_path_repair_slides_a_crossing_path_around_the_zone() -> None:
    """The same crossing path with `slide`: every waypoint whose incoming segment entered goes
    to a nearby point with a free segment, so the path goes on past the zone instead of stopping
    at x = 199; nothing enters, and the last waypoint ends beyond the zone."""
    zone = ZoneSet.from_polygons([rectangle(200, 200, 300, 300)])
    start = torch.tensor([[100.0, 250.0]])
    xs = torch.linspace(140.0, 460.0, 8)
    crossing = torch.stack([xs, torch.full_like(xs, 250.0)], dim=-1)[None]
    sample = torch.cat([torch.tensor([[[250.0, 250.0]]]), crossing], dim=1)
    out = PathRepair(zone, start, first_index=1, margin=1.0)(sample.clone(), make_step(4))
    starts, ends = path_segments(start, out[:, 1:])
    assert not zone.crosses(starts, ends).any()
    assert (zone.signed_distance(out[0, 1:]) >= 1.0 - 1e-6).all()
    assert out[0, -1, 0] > 300.0  # past the zone, not parked in front of it


POSTS = ZoneSet.from_polygons([rectangle(x, y, x + 30, y + 30) for x, y in
                               ((135, 135), (347, 135), (135, 347), (347, 347), (241, 241))]
                              ).inflate(15.0)
coordinate = st.floats(0, 512, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(st.tuples(coordinate, coordinate),
       st.lists(st.tuples(coordinate, coordinate), min_size=8, max_size=8))
@example((0.0, 0.0), [(0.0, 0.0)] * 7 + [(120.0, 347.0)])  # ends on a post's grown corner
@example((0.0, 0.0), [(0.0, 0.0)] * 6 + [(120.0, 347.0), (0.0, 0.0)])
def test_the_sliding_path_repair_never_leaves_a_segment_into_the_area(
        start: tuple, waypoints: list) -> None:
    """From a pusher outside, the repaired path (pusher -> each executed waypoint in turn)
    never enters the area, and no executed waypoint lies in it, wherever the waypoints were."""
    pusher = torch.tensor([start], dtype=torch.float64)
    assume(not bool(POSTS.contains(pusher)[0]))
    sample = torch.tensor([[(256.0, 256.0), *waypoints]], dtype=torch.float64)
    out = PathRepair(POSTS, pusher, first_index=1, margin=1.0)(sample, make_step(4))
    starts, ends = path_segments(pusher, out[:, 1:])
    assert not POSTS.crosses(starts, ends).any()
    assert not POSTS.contains(out[0, 1:]).any()
