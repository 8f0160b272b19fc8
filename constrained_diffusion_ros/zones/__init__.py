"""Restricted zones: polygon geometry the inference hooks consult, and the live id-keyed set."""

from constrained_diffusion_ros.zones.geometry import (
    QUAD_SEGS,
    RestrictedArea,
    ZoneSet,
    rectangle,
    validate_polygon,
)
from constrained_diffusion_ros.zones.live import LiveZones, ZoneId

__all__ = [
    "QUAD_SEGS",
    "LiveZones",
    "RestrictedArea",
    "ZoneId",
    "ZoneSet",
    "rectangle",
    "validate_polygon",
]
