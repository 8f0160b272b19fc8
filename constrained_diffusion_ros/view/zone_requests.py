"""Zones drawn from the live view: the JSON an operator publishes from the Foxglove app's
Publish panel, checked as the policy node checks a zone message before it becomes one.

A request is `{"id": 7, "polygon": [[x, y], ...]}` in workspace px; an empty polygon removes
that id, as on the zones topic. A request that is not that, or whose polygon the policy node
would refuse (too many vertices, not a valid polygon, nothing of it inside the workspace), is
refused here with the reason, so the operator sees why in the view.
"""

from __future__ import annotations

import json
import threading

import numpy as np

from constrained_diffusion_ros.zones.area import Bounds
from constrained_diffusion_ros.zones.geometry import validate_polygon
from msg_schemas.text import one_line

ZONE_REQUEST_SCHEMA_NAME = "constrained_diffusion_ros/ZoneRequest"
ZONE_REQUEST_SCHEMA = {
    "title": "zone request",
    "type": "object",
    "properties": {
        "id": {"type": "integer", "description": "zone id (an existing id is replaced)"},
        "polygon": {"type": "array", "description": "vertices [x, y] in workspace px; [] "
                    "removes the id", "items": {"type": "array", "items": {"type": "number"},
                                                "minItems": 2, "maxItems": 2}}},
    "required": ["id", "polygon"],
}
ZONE_REQUEST_EXAMPLE = {"id": 100, "polygon": [[200, 140], [260, 140], [260, 200], [200, 200]]}
MAX_REQUEST_BYTES = 64 * 1024  # a request is a few hundred bytes; more is refused unread
MAX_PENDING_ZONES = 1000  # ids waiting to be published at most; requests for more are refused
ID_RANGE = (-2**63, 2**63)  # PolygonInstance ids are int64


def parse_zone_request(payload: bytes, max_vertices: int, workspace: Bounds
                       ) -> tuple[int, np.ndarray]:
    """(id, vertices (V, 2)) of a request (V = 0: remove the id), or ValueError in one line."""
    if len(payload) > MAX_REQUEST_BYTES:
        raise ValueError(f"request of {len(payload)} bytes, more than {MAX_REQUEST_BYTES}")
    try:
        request = json.loads(payload)
    except (UnicodeDecodeError, ValueError):
        raise ValueError(f"not JSON: {one_line(repr(bytes(payload[:40])), 60)}") from None
    if not isinstance(request, dict) or set(request) - {"id", "polygon"} \
            or not {"id", "polygon"} <= set(request):
        raise ValueError(f'expected {{"id": <integer>, "polygon": [[x, y], ...]}}, got '
                         f"{one_line(json.dumps(request), 80)}")
    zone_id, polygon = request["id"], request["polygon"]
    if isinstance(zone_id, bool) or not isinstance(zone_id, int) \
            or not ID_RANGE[0] <= zone_id < ID_RANGE[1]:
        raise ValueError(f"id must be a 64-bit integer, got {one_line(json.dumps(zone_id), 40)}")
    if not isinstance(polygon, list):
        raise ValueError(f"zone {zone_id}: polygon must be a list of [x, y]")
    if not polygon:
        return zone_id, np.zeros((0, 2))
    if len(polygon) > max_vertices:
        raise ValueError(f"zone {zone_id}: {len(polygon)} vertices, more than the "
                         f"{max_vertices} allowed")
    if not all(isinstance(v, list) and len(v) == 2 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) for c in v)
            for v in polygon):
        raise ValueError(f"zone {zone_id}: every vertex must be [x, y] numbers")
    vertices = np.asarray(polygon, dtype=float)
    validate_polygon(vertices, f"zone {zone_id}", workspace)
    return zone_id, vertices


class ZoneRequests:
    """Zone requests from the app's clients, taken on the server's threads: checked, coalesced
    to the last per id until `take`n (the node publishes them at its next frame); refusals
    counted (`counts`) with the last reason (`reason`). Only requests on `topic` are taken."""

    def __init__(self, topic: str, max_vertices: int, workspace: Bounds) -> None:
        self.topic, self.max_vertices, self.workspace = topic, max_vertices, workspace
        self.counts = {"zone_messages": 0, "zones_refused": 0}
        self.reason = ""
        self._pending: dict[int, np.ndarray] = {}
        self._channels: dict[tuple[int, int], str] = {}  # (client, channel) -> topic
        self._lock = threading.Lock()

    def advertised(self, client: int, channel: int, topic: str) -> None:
        with self._lock:
            self._channels[(client, channel)] = topic

    def unadvertised(self, client: int, channel: int) -> None:
        with self._lock:
            self._channels.pop((client, channel), None)

    def received(self, client: int, channel: int, payload: bytes) -> None:
        with self._lock:
            self.counts["zone_messages"] += 1
            topic = self._channels.get((client, channel))
        try:
            if topic != self.topic:
                raise ValueError(f"the view takes zones on {self.topic}, not on {topic}")
            zone_id, vertices = parse_zone_request(payload, self.max_vertices, self.workspace)
        except ValueError as error:
            self._refuse(str(error))
            return
        with self._lock:
            if zone_id not in self._pending and len(self._pending) >= MAX_PENDING_ZONES:
                full = True
            else:
                full, self._pending[zone_id] = False, vertices
        if full:
            self._refuse(f"zone {zone_id}: {MAX_PENDING_ZONES} zone requests waiting already")

    def take(self) -> dict[int, np.ndarray]:
        """The requests since the last take, the last per id (vertices (0, 2): remove)."""
        with self._lock:
            pending, self._pending = self._pending, {}
        return pending

    def _refuse(self, reason: str) -> None:
        with self._lock:
            self.counts["zones_refused"] += 1
            self.reason = one_line(reason, 200)
