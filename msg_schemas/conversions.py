"""Message <-> array and stamp <-> control step: the one place these conversions are written.

Readers take rclpy messages and the dataclasses `rosbags` deserialises alike (same field
names), so live nodes and bag readers share them. Builders return rclpy messages and import
their types lazily, so the ROS-free parts of the package can import this module.

Simulated-time topics stamp control step k with k / control_hz seconds, in exact integer
nanoseconds, so a stamp names its step without rounding doubt.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Mapping

import numpy as np

from msg_schemas.contract import FRAME_ID

NANOSECONDS = 1_000_000_000


def stamp_nanoseconds(stamp) -> int:
    return int(stamp.sec) * NANOSECONDS + int(stamp.nanosec)


def stamp_seconds(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def _period_ns(control_hz: float) -> int:
    if not (math.isfinite(control_hz) and control_hz > 0):
        raise ValueError(f"control rate must be positive, got {control_hz}")
    return round(NANOSECONDS / control_hz)


def stamp_of_step(step: int, control_hz: float):
    """builtin_interfaces/Time of control step `step` on simulated time."""
    from builtin_interfaces.msg import Time

    sec, nanosec = divmod(int(step) * _period_ns(control_hz), NANOSECONDS)
    return Time(sec=sec, nanosec=nanosec)


def step_of_stamp(stamp, control_hz: float) -> int:
    """The control step a simulated-time stamp names."""
    return round(stamp_nanoseconds(stamp) / _period_ns(control_hz))


def point_of(msg) -> np.ndarray:
    """(2,) x, y of a PointStamped."""
    return np.array([msg.point.x, msg.point.y])


def polygon_of(polygon) -> np.ndarray:
    """(V, 2) vertices of a geometry_msgs Polygon (the `polygon` of a stamped one)."""
    return np.array([(p.x, p.y) for p in polygon.points], dtype=float).reshape(-1, 2)


def yaw_of(orientation) -> float:
    """Rotation about z of a planar quaternion (x = y = 0)."""
    return 2.0 * math.atan2(orientation.z, orientation.w)


def pose2d_of(msg) -> np.ndarray:
    """(3,) x, y, yaw of a PoseStamped in the plane."""
    pose = msg.pose
    return np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)])


def _header(msg, stamp, frame_id: str = FRAME_ID):
    msg.header.stamp, msg.header.frame_id = stamp, frame_id
    return msg


def point_message(xy: Iterable[float], stamp):
    from geometry_msgs.msg import PointStamped

    msg = _header(PointStamped(), stamp)
    msg.point.x, msg.point.y = (float(v) for v in xy)
    return msg


def polygon_message(vertices: np.ndarray, stamp):
    from geometry_msgs.msg import Point32, PolygonStamped

    msg = _header(PolygonStamped(), stamp)
    msg.polygon.points = [Point32(x=float(x), y=float(y), z=0.0) for x, y in vertices]
    return msg


def pose2d_message(pose: Iterable[float], stamp):
    from geometry_msgs.msg import PoseStamped

    x, y, yaw = (float(v) for v in pose)
    msg = _header(PoseStamped(), stamp)
    msg.pose.position.x, msg.pose.position.y = x, y
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def zone_message(zone_id: int, vertices: np.ndarray | None, stamp):
    """One id-keyed zone; `vertices` None gives the empty polygon that removes the id."""
    from geometry_msgs.msg import Point32, PolygonInstanceStamped

    msg = _header(PolygonInstanceStamped(), stamp)
    msg.polygon.id = int(zone_id)
    if vertices is not None:
        msg.polygon.polygon.points = [Point32(x=float(x), y=float(y), z=0.0) for x, y in vertices]
    return msg


def path_message(waypoints: np.ndarray, stamp):
    """An action chunk (N, 2) as a nav_msgs/Path of planar poses."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    path = _header(Path(), stamp)
    for x, y in waypoints:
        pose = _header(PoseStamped(), stamp)
        pose.pose.position.x, pose.pose.position.y = float(x), float(y)
        pose.pose.orientation.w = 1.0
        path.poses.append(pose)
    return path


def path_of(msg) -> np.ndarray:
    """(N, 2) waypoints of a nav_msgs/Path."""
    return np.array([(p.pose.position.x, p.pose.position.y) for p in msg.poses],
                    dtype=float).reshape(-1, 2)


def zone_markers(outlines: Mapping[int, np.ndarray], stamp, namespace: str = "zones"):
    """One closed red line strip per zone for viewers, its marker id the zone's id (in marker
    namespace `namespace`), outline as received; after a DELETEALL that clears the previous
    set. A zone whose id a marker cannot carry (a name such as "keepout/3", or an integer beyond
    int32, as PolygonInstance ids are int64) goes in `<namespace>/named` with a hashed id, so
    it never shares a marker with a zone of the plain namespace."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker, MarkerArray

    markers = MarkerArray(markers=[Marker(action=Marker.DELETEALL, ns=namespace),
                                   Marker(action=Marker.DELETEALL, ns=f"{namespace}/named")])
    for zone_id, polygon in outlines.items():
        plain = _fits_int32(zone_id)
        marker = _header(Marker(type=Marker.LINE_STRIP, action=Marker.ADD,
                                id=marker_id(zone_id),
                                ns=namespace if plain else f"{namespace}/named"), stamp)
        marker.text = str(zone_id)  # the id itself, for viewers that label zones
        marker.scale.x = 2.0
        marker.color.r, marker.color.a = 1.0, 1.0
        marker.pose.orientation.w = 1.0
        closed = [*polygon, polygon[0]]
        marker.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in closed]
        markers.markers.append(marker)
    return markers


def _fits_int32(zone_id: int | str) -> bool:
    return isinstance(zone_id, int) and -2**31 <= zone_id < 2**31


def marker_id(zone_id: int | str) -> int:
    """A zone's marker id: the zone id itself where a marker's int32 holds it, else a stable
    31-bit hash of the id's text (in the `named` marker namespace, see `zone_markers`)."""
    if _fits_int32(zone_id):
        return zone_id
    return zlib.crc32(str(zone_id).encode()) & 0x7FFFFFFF


def occupancy_grid(values: np.ndarray, resolution: float, origin: Iterable[float], stamp):
    """A keep-out mask (height, width) of int8 as a nav_msgs/OccupancyGrid, row 0 first."""
    from nav_msgs.msg import OccupancyGrid

    msg = _header(OccupancyGrid(), stamp)
    height, width = values.shape
    msg.info.resolution, msg.info.width, msg.info.height = float(resolution), width, height
    msg.info.origin.position.x, msg.info.origin.position.y = (float(v) for v in origin)
    msg.info.origin.orientation.w = 1.0
    msg.data = np.asarray(values, dtype=np.int8).ravel().tolist()
    return msg


def zone_outlines_of(markers) -> dict[str, np.ndarray]:
    """The zones a MarkerArray from `zone_markers` shows: id (as text) -> outline (V, 2)."""
    return {m.text or str(m.id): np.array([(p.x, p.y) for p in m.points[:-1]], dtype=float)
            for m in markers.markers if m.action == m.ADD and len(m.points) > 3}


def zones_shown(markers) -> int:
    """How many zones a MarkerArray from `zone_markers` shows."""
    return sum(m.action == m.ADD for m in markers.markers)
