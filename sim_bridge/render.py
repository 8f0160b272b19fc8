"""Off-screen PushT rendering with Pillow, so images need no display and no pygame.

Pixel (x, y) is workspace (x, y) scaled by size / 512, y pointing down, as the reference draws.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from PIL import Image, ImageDraw

from sim_bridge.scene import (
    AGENT_RADIUS,
    GOAL_POSE,
    WALL_RADIUS,
    WALLS,
    WORKSPACE_SIZE,
    tee_polygons,
)

WHITE = (255, 255, 255)
GOAL_GREEN = (144, 238, 144)  # LightGreen
BLOCK_GREY = (119, 136, 153)  # LightSlateGray
PUSHER_BLUE = (65, 105, 225)  # RoyalBlue
WALL_GREY = (211, 211, 211)  # LightGray
ZONE_RED = (255, 0, 0, 90)  # semi-transparent restricted zones
SETPOINT_RED = (220, 20, 60)  # Crimson
PLAN_ORANGE = (255, 140, 0)  # DarkOrange


def _points(coords: np.ndarray, scale: float) -> list[tuple[float, float]]:
    return [(float(x) * scale, float(y) * scale) for x, y in np.asarray(coords, dtype=float)]


def render_scene(
    state: Sequence[float] | np.ndarray,
    size: int = 512,
    zones: Iterable[np.ndarray | Sequence[Sequence[float]]] = (),
    setpoint: Sequence[float] | np.ndarray | None = None,
    plan: np.ndarray | Sequence[Sequence[float]] | None = None,
) -> np.ndarray:
    """Draw a state [agent x, y, block x, y, angle] as a (size, size, 3) uint8 RGB image.

    zones: polygons (K, 2) in workspace coordinates, drawn as red translucent restricted areas.
    setpoint: commanded pusher target, drawn as a cross. plan: (M, 2) planned points, drawn
    as a polyline with dots.
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 8:
        raise ValueError(f"size must be an int >= 8, got {size!r}")
    st = np.asarray(state, dtype=float)
    if st.shape != (5,) or not np.all(np.isfinite(st)):
        raise ValueError(f"state must be 5 finite numbers, got {st.tolist()}")
    k = size / WORKSPACE_SIZE

    img = Image.new("RGB", (size, size), WHITE)
    draw = ImageDraw.Draw(img)
    for poly in tee_polygons(GOAL_POSE):
        draw.polygon(_points(poly, k), fill=GOAL_GREEN)

    zone_list = [np.asarray(z, dtype=float) for z in zones]
    if zone_list:
        overlay = Image.new("RGBA", (size, size), (0, 0, 0, 0))
        odraw = ImageDraw.Draw(overlay)
        for zone in zone_list:
            if zone.ndim != 2 or zone.shape[1] != 2 or len(zone) < 3:
                raise ValueError(f"each zone must be a (K>=3, 2) polygon, got {zone.shape}")
            odraw.polygon(_points(zone, k), fill=ZONE_RED)
        img = Image.alpha_composite(img.convert("RGBA"), overlay).convert("RGB")
        draw = ImageDraw.Draw(img)

    wall_width = max(1, round(2 * WALL_RADIUS * k))
    for a, b in WALLS:
        draw.line(_points(np.array([a, b]), k), fill=WALL_GREY, width=wall_width)

    for poly in tee_polygons(st[2:5]):
        draw.polygon(_points(poly, k), fill=BLOCK_GREY)

    ax, ay, r = st[0] * k, st[1] * k, AGENT_RADIUS * k
    draw.ellipse((ax - r, ay - r, ax + r, ay + r), fill=PUSHER_BLUE)

    if plan is not None:
        pts = np.asarray(plan, dtype=float).reshape(-1, 2)
        xy = _points(pts, k)
        if len(xy) > 1:
            draw.line(xy, fill=PLAN_ORANGE, width=max(1, round(size / 256)))
        d = max(1.0, size / 170)
        for x, y in xy:
            draw.ellipse((x - d, y - d, x + d, y + d), fill=PLAN_ORANGE)

    if setpoint is not None:
        sx, sy = (float(v) * k for v in np.asarray(setpoint, dtype=float).reshape(2))
        m, w = max(2.0, 8 * size / 512), max(1, round(2 * size / 512))
        draw.line((sx - m, sy, sx + m, sy), fill=SETPOINT_RED, width=w)
        draw.line((sx, sy - m, sx, sy + m), fill=SETPOINT_RED, width=w)

    return np.asarray(img, dtype=np.uint8)
