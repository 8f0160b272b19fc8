"""Zones drawn from the live view: the JSON an operator publishes from the Foxglove app's
Publish panel, checked as the policy node checks a zone message before it becomes one.

A request is `{"id": 7, "polygon": [[x, y], ...]}` in workspace px; an empty polygon removes
that id, as on the zones topic. A request that is not that, or whose polygon the policy node
would refuse (too many vertices, not a valid polygon, nothing of it inside the workspace), is
refused here with the reason, so the operator sees why in the view.
"""

from __future__ import annotations

import json

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
