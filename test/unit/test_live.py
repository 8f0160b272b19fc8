"""The live, id-keyed zone set a node updates from messages."""

from __future__ import annotations

import pytest

from constrained_diffusion_ros.zones import LiveZones, rectangle


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
