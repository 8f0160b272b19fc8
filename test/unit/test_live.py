"""The live, id-keyed zone set a node updates from messages."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from constrained_diffusion_ros.zones import LiveZones, rectangle
from constrained_diffusion_ros.zones.live import coalesce


def test_live_zones_bookkeeping() -> None:
    live = LiveZones()
    square = rectangle(0, 0, 10, 10)
    live.upsert("a", square, now=0.0)
    live.upsert(7, rectangle(20, 0, 30, 10), now=0.0, lifetime=5.0)
    assert live.ids == ["a", 7] and live.version == 2
    first = live.snapshot()
    assert first is live.snapshot() and first.area == pytest.approx(200)

    live.upsert("a", rectangle(0, 0, 20, 10), now=1.0)  # replace: now touches zone 7
    assert live.version == 3 and len(live.snapshot()) == 1 and first.area == pytest.approx(200)

    with pytest.raises(ValueError, match="zone 'a'"):
        live.upsert("a", [[0, 0], [1, 1], [1, 0], [0, 1]], now=2.0)
    assert live.version == 3 and live.snapshot().area == pytest.approx(300)

    assert live.expire(now=4.9) == [] and live.expire(now=5.0) == [7]
    assert live.version == 4 and live.snapshot().area == pytest.approx(200)

    live.upsert("a", [], now=6.0)  # empty polygon removes the id
    assert live.ids == [] and live.version == 5 and live.snapshot().is_empty
    assert not live.remove("a") and live.version == 5

    live.upsert("b", square, now=7.0)
    live.clear()
    assert len(live) == 0 and live.version == 7


def test_a_batch_keeps_the_last_message_per_id_and_loses_none() -> None:
    """A flood taken in one batch: every id ends as its last message said, in one change."""
    live = LiveZones()
    messages = []
    for t in range(1000):  # ids 0..9 updated over and over, id 3 removed at the end
        zone_id = t % 10
        messages.append((zone_id, rectangle(t, 0, t + 5, 5)))
    messages.append((3, []))
    assert list(coalesce(messages)) == [0, 1, 2, 4, 5, 6, 7, 8, 9, 3]
    outcome = live.apply(messages, now=0.0)
    assert outcome.received == 1001 and outcome.superseded == 991 and outcome.refused == []
    assert outcome.changed and live.version == 9  # 9 added; 3 never existed, so not removed
    snapshot = live.snapshot()
    for zone_id in live.ids:
        last = 990 + zone_id
        assert snapshot.contains(torch.tensor([[last + 2.5, 2.5]])).item()
    assert sorted(live.ids) == [0, 1, 2, 4, 5, 6, 7, 8, 9]


def test_caps_refuse_with_a_reason_and_keep_the_zones_in_force() -> None:
    live = LiveZones(max_zones=2, max_vertices=5)
    live.apply([(1, rectangle(0, 0, 1, 1)), (2, rectangle(2, 0, 3, 1))], now=0.0)
    hexagon = [[0, 0], [1, 0], [1, 1], [0.5, 1.5], [0, 1], [-0.5, 0.5]]
    outcome = live.apply([(3, rectangle(4, 0, 5, 1)), (1, hexagon),
                          (2, [[0, 0], [float("nan"), 0], [1, 1]])], now=0.0)
    reasons = dict(outcome.refused)
    assert "cap" in reasons[3] and "6 vertices" in reasons[1] and "finite" in reasons[2]
    assert outcome.applied == 0 and not outcome.changed and live.ids == [1, 2]
    outcome = live.apply([(1, []), (3, rectangle(4, 0, 5, 1))], now=0.0)  # room made first
    assert outcome.refused == [] and live.ids == [2, 3]
    # Zones the node derives itself (a keep-out mask's pieces) are not held to the caps.
    outcome = live.apply([("keepout/0", hexagon), ("keepout/1", rectangle(8, 0, 9, 1))],
                         now=0.0, capped=False)
    assert outcome.refused == [] and live.ids == [2, 3, "keepout/0", "keepout/1"]
    # ... nor counted toward them: with a mask in force, a message's zone still finds room.
    outcome = live.apply([(2, []), (4, rectangle(10, 0, 11, 1))], now=0.0)
    assert outcome.refused == [] and live.ids == [3, "keepout/0", "keepout/1", 4]


def test_lifetime_counts_from_the_stamp_so_a_replayed_stale_zone_stays_gone() -> None:
    live = LiveZones()
    square = rectangle(10, 10, 20, 20)
    outcome = live.apply([(1, square, 95.0), (2, square, 99.0), (3, square, None)], now=100.0,
                         lifetime=2.0)
    assert live.ids == [2, 3] and outcome.applied == 2 and outcome.stale == 1
    assert live.expire(101.5) == [2]  # published at 99: gone at 101, not at 102
    assert live.expire(102.5) == [3]  # no stamp: counted from its arrival at 100
    live.apply([(4, square, 500.0)], now=100.0, lifetime=2.0)  # a stamp from the future
    assert live.expire(102.5) == [4]  # ... counts as now, so it cannot outlive its lifetime
    assert set(live.outlines()) == set()
    live.apply([(5, square)], now=100.0)
    np.testing.assert_array_equal(live.outlines()[5], square)


WORKSPACE = (0.0, 0.0, 512.0, 512.0)


def test_a_zone_beyond_the_workspace_is_clipped_so_what_is_accepted_is_enforced() -> None:
    """A square from -1e30 to 1e30 used to be accepted and then grow into nothing; clipped,
    it is the workspace, and grown by the pusher radius it still holds every point."""
    live = LiveZones(workspace=WORKSPACE)
    live.apply([(1, rectangle(-1e30, -1e30, 1e30, 1e30))], now=0.0)
    area = live.snapshot()
    assert area.area == pytest.approx(512.0 * 512.0)
    points = torch.rand(200, 2, dtype=torch.float64) * 512.0
    assert area.inflate(15.0).contains(points).all()
    outcome = live.apply([(2, rectangle(600, 600, 700, 700))], now=0.0)  # wholly outside
    assert outcome.refused and "outside the workspace" in outcome.refused[0][1]


def test_slivers_and_specks_are_refused_and_the_zones_in_force_stay() -> None:
    live = LiveZones(workspace=WORKSPACE)
    live.apply([(1, rectangle(10, 10, 50, 50))], now=0.0)
    # Collinear points rounded to float32: a zero-area sliver 300 px long.
    line = np.array([[0.1, 0.1], [300.1, 200.1], [150.1, 100.1]], dtype=np.float32)
    tiny = rectangle(100, 100, 100.5, 100.5)
    thin = [[0.0, 0.0], [300.0, 1.0], [600.0, 2.5]]  # 1.5 px^2 over 300 px, clipped: a sliver
    outcome = live.apply([(2, line.astype(float)), (3, tiny), (4, thin)], now=0.0)
    reasons = dict(outcome.refused)
    assert set(reasons) == {2, 3, 4} and live.ids == [1]
    assert "area" in reasons[2] and "area" in reasons[3] and "sliver" in reasons[4]


def test_after_a_clear_a_replay_of_a_cleared_message_is_stale() -> None:
    """Exact replays (id and stamp) only: whatever clock the stamps come from, a new message
    for the id, even stamped earlier (a sim clock that restarted), is taken."""
    zones = LiveZones()
    zones.upsert(1, rectangle(0, 0, 10, 10), now=5.0, stamp=4.0)
    zones.upsert(2, rectangle(20, 20, 30, 30), now=5.0)  # unstamped: cannot be told apart
    zones.clear()
    assert list(zones.cleared) == [(1, 4.0)] and zones.ids == []
    assert not zones.upsert(1, rectangle(0, 0, 10, 10), now=6.0, stamp=4.0)  # replayed
    assert zones.ids == []
    assert zones.upsert(1, rectangle(0, 0, 10, 10), now=6.0, stamp=0.5)  # a new message
    assert zones.upsert(3, rectangle(20, 20, 30, 30), now=6.0, stamp=4.0)
    assert zones.ids == [1, 3]


def test_a_moving_zone_within_the_reach_assumed_of_it_needs_no_answer_of_its_own() -> None:
    """A hand republished at 20 Hz: once it is seen moving, an update that stays within what
    it was assumed able to reach (its assumed speed times the time between the two) leaves
    the setpoints checked before sound; a faster jump, a zone that grows beyond that reach, a
    new zone and a removal are not within reach (the node answers them at once)."""
    zones = LiveZones()

    def update(x: float, stamp: float, side: float = 20.0) -> bool:
        outcome = zones.apply([(1, rectangle(x, 100, x + side, 100 + side), stamp)], now=10.0)
        assert outcome.changed
        return outcome.within_reach

    assert not update(100, 9.00)  # new
    assert not update(105, 9.05)  # first seen moving: it was taken to stand still
    assert update(110, 9.10) and update(115, 9.15)  # 100 px/s, 150 px/s assumed
    assert not update(135, 9.20)  # 400 px/s
    assert not update(140, 9.25, side=40)  # 5 px on, but 20 px wider: beyond 300 px/s x 50 ms
    removed = zones.apply([(1, [], 9.30)], now=10.0)
    assert removed.changed and not removed.within_reach
