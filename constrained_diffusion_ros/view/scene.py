"""The PushT scene as Foxglove's well-known schemas: what the live view draws, top down.

Everything is in the workspace frame (px, origin top-left, y down, as the image). The view frame
`VIEW_FRAME` puts the workspace's centre at its origin with y up the screen, so the Foxglove 3D
panel's 2D (top-down) camera shows the scene as the simulator renders it: `view_transform`.
The scene is a pure function of `SceneState`, so it can be tested and replayed without a server.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import shapely
from foxglove.messages import (
    Color,
    CylinderPrimitive,
    FrameTransform,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from constrained_diffusion_ros.zones.geometry import QUAD_SEGS
from msg_schemas import FRAME_ID
from msg_schemas.conversions import path_of, point_of, pose2d_of, zone_outlines_of
from msg_schemas.text import one_line
from sim_bridge.scene import GOAL_POSE, WALLS, WORKSPACE_SIZE, tee_polygons

VIEW_FRAME = "view"  # the workspace's centre, x right and y up the screen

WALL = Color(r=0.55, g=0.55, b=0.6, a=1.0)
GOAL = Color(r=0.2, g=0.75, b=0.3, a=1.0)
BLOCK = Color(r=0.45, g=0.55, b=0.7, a=0.9)
PUSHER = Color(r=0.25, g=0.45, b=0.95, a=0.9)
SETPOINT = Color(r=1.0, g=0.85, b=0.1, a=1.0)
PLAN = Color(r=1.0, g=0.6, b=0.1, a=1.0)
ZONE = Color(r=0.9, g=0.15, b=0.15, a=0.45)
ZONE_EDGE = Color(r=0.9, g=0.15, b=0.15, a=1.0)
INFLATED = Color(r=0.9, g=0.4, b=0.4, a=0.8)
TEXT = Color(r=1.0, g=1.0, b=1.0, a=1.0)
ALERT = Color(r=1.0, g=0.35, b=0.3, a=1.0)
LIFT = 0.5  # px above the workspace plane per layer: later layers draw over earlier ones


@dataclass
class SceneState:
    """What the view knows of the robot, each part as its topic last said (None: not yet)."""
    pusher: np.ndarray | None = None  # (2,) px
    setpoint: np.ndarray | None = None  # (2,) px
    block_pose: np.ndarray | None = None  # (x, y, angle)
    plan: np.ndarray | None = None  # (N, 2) px, the chunk in force
    zones: dict[str, np.ndarray] = field(default_factory=dict)  # id -> outline (V, 2) in force
    score: float | None = None
    inflate_px: float = 0.0  # > 0: also outline the zones grown by this much (the planner's)
    pusher_radius: float = 15.0
    filter_state: str = ""  # "held", "shielded", "cornered", "no free space", or ""
    policy_status: str = ""  # the policy node's diagnostic message
    refusal: str = ""  # why the last zone was refused (the view's or the policy's)
    policy_refusal: str = ""  # the policy node's last zone refusal


# Scene state part <- (contract topic, its message converted): live and from a bag alike.
PARTS = {"pusher": ("pusher", point_of), "setpoint": ("setpoint", point_of),
         "block_pose": ("block_pose", pose2d_of), "plan": ("plan", path_of),
         "zones": ("zone_markers", zone_outlines_of), "score": ("score", lambda m: float(m.data))}
FILTER_STATES = (("no_free_space", "no free space"), ("cornered", "cornered"),
                 ("holding", "held"), ("shielded", "shielded"))


def take_policy_status(state: SceneState, message: str, values: dict[str, str],
                       inflating: set[str]) -> None:
    """The policy node's /diagnostics into the scene: its message, the filter's state, whether
    its configuration (one of `inflating`) grows the zones (by the pusher's radius), and its
    last zone refusal."""
    state.inflate_px = state.pusher_radius if values.get("configuration") in inflating else 0.0
    state.filter_state = ", ".join(name for key, name in FILTER_STATES
                                   if values.get(key) == "True")
    state.policy_status = one_line(message, 120)
    refusal = values.get("zone_refusal", "")
    if refusal and refusal != state.policy_refusal:  # news: shown until another refusal
        state.policy_refusal = state.refusal = refusal


def view_transform(stamp_ns: int = 0) -> FrameTransform:
    """VIEW_FRAME -> workspace: a half turn about x (y down becomes y up) and the centre to the
    origin."""
    half = WORKSPACE_SIZE / 2
    return FrameTransform(timestamp=_timestamp(stamp_ns), parent_frame_id=VIEW_FRAME,
                          child_frame_id=FRAME_ID,
                          translation=Vector3(x=-half, y=half, z=0.0),
                          rotation=Quaternion(x=1.0, y=0.0, z=0.0, w=0.0))


def scene_update(state: SceneState, stamp_ns: int = 0) -> SceneUpdate:
    """The whole scene (every entity replaced; zones no longer in force deleted first)."""
    stamp = _timestamp(stamp_ns)
    entities = [_entity("workspace", stamp, lines=[_segments(np.asarray(WALLS), WALL, 4.0)]),
                _entity("goal", stamp, lines=[_outline(p, GOAL, 2.0, 1)
                                              for p in tee_polygons(GOAL_POSE)])]
    if state.block_pose is not None:
        parts = [shapely.Polygon(part) for part in tee_polygons(state.block_pose)]
        entities.append(_entity("block", stamp, triangles=[_fill(parts, BLOCK, 2)]))
    for zone_id, outline in sorted(state.zones.items()):
        drawing = _zone_drawing(zone_id, np.asarray(outline, dtype=float).tobytes(),
                                state.inflate_px)
        entities.append(_entity(f"zone/{zone_id}", stamp, **drawing))
    if state.plan is not None and len(state.plan):
        entities.append(_entity("plan", stamp, lines=[_strip(state.plan, PLAN, 1.5, 5)],
                                spheres=[_sphere(p, 4.0, PLAN, 5) for p in state.plan]))
    if state.pusher is not None:
        entities.append(_entity("pusher", stamp, cylinders=[CylinderPrimitive(
            pose=_pose(state.pusher, 4), color=PUSHER,
            size=Vector3(x=2 * state.pusher_radius, y=2 * state.pusher_radius, z=1.0))]))
    if state.setpoint is not None:
        entities.append(_entity("setpoint", stamp,
                                spheres=[_sphere(state.setpoint, 8.0, SETPOINT, 6)]))
    entities.append(_entity("status", stamp, texts=_status_texts(state)))
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp,
                                                      type=SceneEntityDeletionType.All)],
                       entities=entities)


def triangles(polygon: shapely.Geometry) -> np.ndarray:
    """(T, 3, 2) triangles covering a polygon (holes and concave parts kept out)."""
    pieces = shapely.get_parts(shapely.constrained_delaunay_triangles(polygon))
    return np.array([np.asarray(t.exterior.coords)[:3] for t in pieces]).reshape(-1, 3, 2)


# -- entities ---------------------------------------------------------------------------------

@functools.lru_cache(maxsize=1024)
def _zone_drawing(zone_id: str, outline_bytes: bytes, inflate_px: float) -> dict[str, list]:
    """A zone's primitives, kept while its outline and the inflation stay the same: zones
    change far less often than frames are drawn, and the triangulation and the grown outline
    are most of a frame's work."""
    outline = np.frombuffer(outline_bytes).reshape(-1, 2)
    polygon = shapely.make_valid(shapely.Polygon(outline))
    lines = [_outline(outline, ZONE_EDGE, 2.0, 3)]
    if inflate_px > 0:  # where the pusher's centre may not go: the planner's grown zone
        grown = shapely.buffer(polygon, inflate_px, quad_segs=QUAD_SEGS)
        lines += [_outline(np.asarray(p.exterior.coords)[:-1], INFLATED, 1.0, 3)
                  for p in shapely.get_parts(grown)]
    top = outline[np.argmin(outline[:, 1])]
    label = TextPrimitive(pose=_pose(top - (0.0, 10.0), 7), billboard=True, font_size=14,
                          scale_invariant=True, color=ZONE_EDGE, text=f"zone {zone_id}")
    return {"lines": lines, "texts": [label], "triangles": [_fill([polygon], ZONE, 3)]}


def _status_texts(state: SceneState) -> list[TextPrimitive]:
    score = "score -" if state.score is None else f"score {state.score:.3f}"
    lines = [(f"{score}   filter: {state.filter_state or 'free'}",
              ALERT if state.filter_state else TEXT)]
    if state.policy_status:
        lines.append((f"policy: {state.policy_status}", TEXT))
    if state.refusal:
        lines.append((f"zone refused: {state.refusal}", ALERT))
    return [TextPrimitive(pose=_pose((8.0, -14.0 - 18.0 * k), 8), billboard=True,
                          font_size=16, scale_invariant=True, color=color, text=text)
            for k, (text, color) in enumerate(lines)]


def _entity(entity_id: str, stamp: Timestamp, **primitives) -> SceneEntity:
    return SceneEntity(timestamp=stamp, frame_id=FRAME_ID, id=entity_id, **primitives)


def _points(xy: np.ndarray, layer: int) -> list[Point3]:
    # Above the plane is -z in the workspace frame (z points into the screen, y being down).
    return [Point3(x=float(x), y=float(y), z=-LIFT * layer) for x, y in np.asarray(xy)]


def _pose(xy, layer: int) -> Pose:
    return Pose(position=Vector3(x=float(xy[0]), y=float(xy[1]), z=-LIFT * layer),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _strip(points: np.ndarray, color: Color, thickness: float, layer: int) -> LinePrimitive:
    return LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=thickness,
                         points=_points(points, layer), color=color, pose=_pose((0, 0), 0))


def _outline(vertices: np.ndarray, color: Color, thickness: float, layer: int) -> LinePrimitive:
    closed = np.vstack([vertices, vertices[:1]])
    return _strip(closed, color, thickness, layer)


def _segments(pairs: np.ndarray, color: Color, thickness: float) -> LinePrimitive:
    return LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=thickness,
                         points=_points(pairs.reshape(-1, 2), 0), color=color,
                         pose=_pose((0, 0), 0))


def _fill(polygons: list[shapely.Geometry], color: Color, layer: int) -> TriangleListPrimitive:
    pieces = [triangles(polygon) for polygon in polygons]
    return TriangleListPrimitive(points=_points(np.concatenate(pieces).reshape(-1, 2), layer),
                                 color=color, pose=_pose((0, 0), 0))


def _sphere(xy, size: float, color: Color, layer: int) -> SpherePrimitive:
    return SpherePrimitive(pose=_pose(xy, layer), size=Vector3(x=size, y=size, z=size),
                           color=color)


def _timestamp(stamp_ns: int) -> Timestamp:
    return Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
