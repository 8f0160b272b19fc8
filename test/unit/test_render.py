"""Off-screen rendering of the scene, with zones, setpoint and plan drawn over it."""

from __future__ import annotations

import numpy as np
import pytest

from sim_bridge.physics import PushTBatch, PushTSim
from sim_bridge.render import BLOCK_GREY, GOAL_GREEN, PUSHER_BLUE, render_scene
from sim_bridge.scene import seeded_state


def _has_colour(img: np.ndarray, rgb: tuple[int, int, int]) -> bool:
    return bool(np.any(np.all(img == np.array(rgb, dtype=np.uint8), axis=-1)))


@pytest.mark.parametrize("size", [96, 512])
def test_render_draws_scene(size: int) -> None:
    sim = PushTSim()
    sim.reset(0)
    img = sim.render(size=size)
    assert img.shape == (size, size, 3) and img.dtype == np.uint8
    for colour in (GOAL_GREEN, BLOCK_GREY, PUSHER_BLUE):
        assert _has_colour(img, colour), colour


def test_render_overlays() -> None:
    state = seeded_state(0)
    zone = np.array([[20.0, 20.0], [120.0, 20.0], [120.0, 120.0], [20.0, 120.0]])
    img = render_scene(
        state, size=256, zones=[zone], setpoint=[400.0, 60.0], plan=[[300, 300], [350, 350]]
    )
    assert img.shape == (256, 256, 3)
    r, g, b = img[35, 35].astype(int)  # inside the zone, on white: tinted red
    assert r == 255 and g < 255 and b < 255
    assert tuple(img[30, 200]) == (220, 20, 60)  # setpoint cross centre at (400, 60) * 0.5
    batch = PushTBatch(2)
    batch.reset([0, 1])
    assert batch.render(1, size=64).shape == (64, 64, 3)
