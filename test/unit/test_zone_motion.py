"""Zone motion: a velocity per id from its stamped updates, the speed a guarantee assumes of
each, and the live zone set keeping it as zones come, move and go."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch
from hypothesis import given
from hypothesis import strategies as st

from constrained_diffusion_ros.zones.geometry import ZoneSet, rectangle
from constrained_diffusion_ros.zones.live import MAX_FORECAST, LiveZones
from constrained_diffusion_ros.zones.motion import (
    COVER_PX,
    FLOOR,
    HEADROOM,
    JUMP_PX,
    MAX_GAP_S,
    MovingZones,
    ZoneMotion,
    cover,
)

pytestmark = pytest.mark.unit


def square(x: float, y: float, side: float = 50.0) -> np.ndarray:
    return np.array([(x, y), (x + side, y), (x + side, y + side), (x, y + side)])


@given(vx=st.floats(-400, 400), vy=st.floats(-400, 400), rate=st.sampled_from([10.0, 20.0, 50.0]))
def test_a_zone_moving_steadily_is_measured_at_its_velocity(vx: float, vy: float,
                                                            rate: float) -> None:
    motion = ZoneMotion(speed_bound=1000.0)
    for k in range(6):
        t = k / rate
        motion.observe(7, (100 + vx * t, 200 + vy * t), t)
    assert motion.measured(7)
    assert np.allclose(motion.velocity(7), (vx, vy), atol=1e-6)
    assert motion.speed(7) == pytest.approx(np.hypot(vx, vy), abs=1e-6)


def test_a_zone_stands_still_until_an_update_shows_it_moving_then_keeps_its_own_bound() -> None:
    """The assumption a guarantee rests on: published once or republished in place, a zone
    stands still; once an update has displaced it, it may move at HEADROOM times the fastest
    it was measured at (at least FLOOR, at most the bound), paused or not, since a hand may
    set off again at any time; with headroom 0, at the bound."""
    motion = ZoneMotion(speed_bound=250.0)
    assert motion.assumed_speed("unknown") == 0.0 and motion.speed("unknown") == 0.0
    for k in range(4):  # republished in place
        motion.observe(1, (100.0, 100.0), 0.1 * k)
    assert motion.measured(1) and not motion.moving(1) and motion.assumed_speed(1) == 0.0
    motion.observe(2, (100.0, 100.0), 0.0)
    motion.observe(2, (101.0, 100.0), 0.1)  # 10 px/s
    assert not motion.measured(2) and motion.speed(2) == 0.0  # too few updates to measure
    assert motion.moving(2) and motion.assumed_speed(2) == FLOOR
    motion.observe(2, (105.0, 100.0), 0.2)  # 40 px/s: within the floor assumed
    assert motion.measured(2) and motion.assumed_speed(2) == pytest.approx(HEADROOM * 40.0)
    for k in range(3, 8):  # then it pauses
        motion.observe(2, (105.0, 100.0), 0.1 * k)
    assert motion.speed(2) < 5.0 and motion.assumed_speed(2) == pytest.approx(HEADROOM * 40)
    assert motion.exceeded == 0
    motion.observe(2, (135.0, 100.0), 0.8)  # 300 px/s: faster than assumed, and the bound
    assert motion.exceeded == 1 and motion.assumed_speed(2) == 250.0
    strict = ZoneMotion(speed_bound=250.0, headroom=0.0)
    strict.observe(3, (0.0, 0.0), 0.0)
    strict.observe(3, (1.0, 0.0), 0.1)
    assert strict.assumed_speed(3) == 250.0


def test_replays_and_pauses_say_nothing_of_motion() -> None:
    """A replay (same stamp, or older) is not a displacement in no time; after a pause longer
    than MAX_GAP_S the estimate starts afresh, not averaged over the pause."""
    motion = ZoneMotion()
    for k in range(4):
        motion.observe(1, (100.0 + 10 * k, 100.0), 0.1 * k)
    motion.observe(1, (500.0, 500.0), 0.3)  # a replay of the last stamp, elsewhere
    motion.observe(1, (0.0, 0.0), 0.1)  # out of order
    assert motion.speed(1) == pytest.approx(100.0)
    motion.observe(1, (400.0, 100.0), 0.3 + MAX_GAP_S + 0.5)
    assert not motion.measured(1)


def test_a_zone_faster_than_the_bound_is_named() -> None:
    motion = ZoneMotion(speed_bound=100.0)
    for k in range(4):
        motion.observe("fast", (25.0 * k, 0.0), 0.1 * k)  # 250 px/s
        motion.observe("slow", (5.0 * k, 0.0), 0.1 * k)  # 50 px/s
    assert motion.over_bound() == ["fast"]


def test_the_live_zones_measure_a_republished_zone_and_forget_one_that_goes() -> None:
    zones = LiveZones(speed_bound=300.0)
    for k in range(5):  # 100 px/s to the right, republished at 10 Hz with its stamp
        zones.upsert(3, square(100 + 10 * k, 100), now=0.1 * k + 0.01, stamp=0.1 * k)
    assert zones.motion.speed(3) == pytest.approx(100.0)
    zone_id, distance, speed, assumed = zones.nearest((160.0, 300.0))  # below 140..190 x 100..150
    assert zone_id == 3 and distance == pytest.approx(150.0) and speed == pytest.approx(100.0)
    assert assumed == pytest.approx(HEADROOM * 100.0)
    assert zones.nearest((170.0, 120.0))[1] == 0.0  # inside
    zones.upsert(3, [], now=1.0)
    assert not zones.motion.measured(3) and zones.nearest((0.0, 0.0)) is None
    zones.upsert(4, square(0, 0), now=2.0)  # unstamped: measured on the node's clock
    zones.upsert(4, square(20, 0), now=2.1)
    zones.upsert(4, square(40, 0), now=2.2)
    assert zones.motion.speed(4) == pytest.approx(200.0)
    zones.clear()
    assert zones.motion.speed(4) == 0.0 and not zones.motion.moving(4)


def test_the_live_zones_hand_a_shield_the_moving_ones_apart_and_aged() -> None:
    """A zone republished in place stays a plain zone; one that moves comes as `MovingZones`,
    its reach growing with the time since it was where it is (its stamp's age on arrival
    included) and with the robot's reaction, and every other query answering for the zones as
    they are."""
    zones = LiveZones(speed_bound=300.0, reaction_s=0.4)
    for k in range(3):
        zones.upsert("still", square(300, 300), now=100.0 + 0.1 * k, stamp=100.0 + 0.1 * k)
    assert not isinstance(zones.area_at(0), MovingZones)
    for k in range(3):  # 100 px/s, each update 0.05 s old when it arrives
        zones.upsert("hand", square(100 + 10 * k, 100), now=100.05 + 0.1 * k,
                     stamp=100.0 + 0.1 * k)
    area = zones.area_at(0)
    assert isinstance(area, MovingZones) and float(area.speed) == pytest.approx(150.0)
    assert 0.05 <= float(area.age_s) < 0.5
    grown = float(area.reach())
    assert grown == pytest.approx(150.0 * (float(area.age_s) + 0.4))
    # 30 px right of the hand (last at x 120..170), 10 px below the still zone
    probe = torch.tensor([[200.0, 125.0], [325.0, 360.0]])
    now, later = area.signed_distance(probe), area.signed_distance_after(probe, 0.4)
    assert now.tolist() == pytest.approx([30.0, 10.0])
    # (the moving zone checked as its cover: up to 2 COVER_PX nearer, never farther)
    assert 30.0 - grown - 2 * COVER_PX <= later[0] <= 30.0 - grown
    assert later[1] == pytest.approx(10.0)
    assert area.contains(torch.tensor([[130.0, 120.0]])).item()  # the hand as it is


def test_plans_see_a_moving_zone_where_it_will_be_when_each_waypoint_runs() -> None:
    """`MovingZones.ahead`: waypoint h is checked against the zone carried on at its measured
    velocity for seconds[h], in every query the hooks make (inside, distance, projection, one
    moment per row for path repair); without a measured velocity the zones are as they are."""
    zone = ZoneSet.from_polygons([np.array([(0, 0), (20, 0), (20, 20), (0, 20)])])
    velocity = torch.tensor([[100.0, 0.0], [0.0, 100.0]])  # per row
    area = MovingZones(zone, ZoneSet.empty(), zone, 150.0, 0.0, 0.4, drift=[(zone, velocity)])
    forecast = area.ahead(torch.arange(4, dtype=torch.float64) * 0.1)  # 10 px a waypoint
    riding = torch.tensor([[[15.0 + 10 * h, 10.0] for h in range(4)],
                           [[10.0, 15.0 + 10 * h] for h in range(4)]])
    assert forecast.contains(riding).all()
    waiting = torch.tensor([[[15.0, 10.0]] * 4] * 2)  # where the zone is now
    assert forecast.contains(waiting).tolist() == [[True, True, False, False]] * 2
    out = forecast.project_out(riding, 1.0)
    assert (forecast.signed_distance(out) >= 1.0 - 1e-6).all()
    later = forecast.columns(2).select_rows(torch.tensor([1])).at(torch.tensor([1]))
    assert later.contains(torch.tensor([[[10.0, 45.0]]])).item()  # row 1 at 0.3 s: y 30..50
    with pytest.raises(ValueError, match="chunks of 4 waypoints"):
        forecast.contains(torch.zeros(2, 3, 2))
    unmeasured = MovingZones(zone, ZoneSet.empty(), zone, 150.0, 0.0, 0.4)
    assert unmeasured.ahead(torch.zeros(4)) is zone


@pytest.mark.parametrize("vertices", [4, 7, 64])
@pytest.mark.parametrize("radius", [6.0, 30.0, 200.0])
def test_a_moving_zone_is_checked_as_few_edges_that_cover_it(vertices: int,
                                                            radius: float) -> None:
    """`cover`: a convex outline that holds the zone and lies at most 2 COVER_PX beyond its
    hull, with far fewer edges than the cap's 64 where the zone is round and small."""
    angles = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
    zone = shapely.Polygon(256 + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1))
    outline = cover(zone)
    assert outline.covers(zone)
    assert zone.convex_hull.hausdorff_distance(outline) <= 2 * COVER_PX + 1e-9
    assert len(outline.exterior.coords) - 1 <= (vertices if radius > 100 else 16)


def test_plans_forecast_a_few_believable_moving_zones_and_take_the_rest_where_they_are() -> None:
    """A flood of moving ids costs the plans at most MAX_FORECAST forecasts: the fastest
    within the bound. One measured faster than the bound is not forecast (its velocity is not
    believed) but the plans still avoid it where it is, and the shield grows it at the
    bound."""
    zones = LiveZones(speed_bound=300.0)
    for k in range(4):
        t = 100.0 + 0.1 * k
        for i in range(8):  # 10..80 px/s, rising with the id
            zones.upsert(i, square(20 + 55 * i + (i + 1) * k, 300), now=t, stamp=t)
        zones.upsert("too fast", square(20 + 60 * (k % 2), 100), now=t, stamp=t)  # 600 px/s
    forecast = zones.forecast(zones.ids)
    assert forecast == tuple(range(7, 7 - MAX_FORECAST, -1))
    area = zones.area_at(0)
    assert len(area.drift) == MAX_FORECAST and float(area.speed) == 300.0
    chunk = torch.tensor([[[105.0, 125.0]] * 4])  # inside the fast one, where it is now
    assert zones.area_at(0).ahead(torch.arange(4) * 0.1).contains(chunk).all()
    assert area.signed_distance_after(torch.tensor([[105.0, 200.0]]), 0.4) < 0  # 50 px below


def test_a_zone_scattered_faster_than_any_hand_is_placed_anew_not_grown() -> None:
    """An update beyond JUMP x the bound re-places the zone: it stands still there, as a new
    zone does, and so do its updates until MAX_GAP_S passes without a jump (a flood of
    scattered ids, some of whose updates look like motion by chance, is not a swarm of hands
    each grown by the bound). A hand faster than the bound but within JUMP of it moves."""
    zones = LiveZones(speed_bound=300.0)
    xs = [20, 320, 330, 340, 350]  # a jump (6000 px/s), then 200 px/s
    for k, x in enumerate(xs):
        t = 100.0 + 0.05 * k
        zones.upsert("scattered", square(x, 400), now=t, stamp=t)
        zones.upsert("fast hand", square(20 + 30 * k, 100), now=t, stamp=t)  # 600 px/s
    assert zones.motion.jumps == 1
    assert not zones.motion.moving("scattered") and zones.motion.moving("fast hand")
    assert zones.motion.over_bound() == ["fast hand"]
    beside = torch.tensor([[375.0, 395.0]])  # 5 px above the scattered zone as it is now
    assert zones.area_at(0).signed_distance_after(beside, 0.4).item() == pytest.approx(5.0)
    t = 100.2 + MAX_GAP_S  # a second without a jump: its next displacement is motion again
    zones.upsert("scattered", square(360, 400), now=t, stamp=t)
    zones.upsert("scattered", square(370, 400), now=t + 0.05, stamp=t + 0.05)
    assert zones.motion.moving("scattered")


def test_a_hand_whose_stamps_come_close_together_still_moves() -> None:
    """Stamps 2 ms apart (a tracker's jitter, a publisher behind on a busy machine) make a
    15 px step of a hand look like 7,500 px/s: within JUMP_PX it is still motion, not a jump
    that would have the hand taken as standing still."""
    motion = ZoneMotion(speed_bound=300.0)
    stamps = [0.0, 0.05, 0.052, 0.1, 0.15, 0.152]
    for k, stamp in enumerate(stamps):
        motion.observe("hand", (100.0 + 15.0 * k, 100.0), stamp)
    assert motion.jumps == 0 and motion.moving("hand")
    motion.observe("hand", (100.0 + 15.0 * 6 + JUMP_PX + 1.0, 100.0), 0.152 + 1e-6)
    assert motion.jumps == 1 and not motion.moving("hand")


def test_an_inflated_moving_zone_is_grown_in_its_distance_not_buffered() -> None:
    """Inflated by a pusher's radius, the moving part keeps its few edges and is grown in its
    signed distance, as its motion grows it: exact outside it (a buffer's round joins made a
    flood of ids taken for moving cost a shield call most of a second)."""
    hand = ZoneSet.from_polygons([rectangle(0, 0, 20, 20)])
    area = MovingZones(hand, ZoneSet.empty(), hand, 100.0, 0.1, 0.45).inflate(15.0)
    assert area.moving is hand and area.radius == 15.0
    points = torch.tensor([[40.0, 10.0], [10.0, 10.0], [35.0, 35.0], [-30.0, 5.0]])
    expected = hand.signed_distance(points) - 15.0 - 100.0 * (0.1 + 0.2)
    assert torch.allclose(area.signed_distance_after(points, 0.2), expected, atol=1e-4)
    assert torch.allclose(area.moving_distance(points), hand.signed_distance(points) - 15.0)
