"""Restricted zones: the area protocol every check implements (`area`), exact polygon unions
(`geometry`), different zones per episode of a batch (`episodes`), and the live id-keyed set a
node updates from messages (`live`)."""

from constrained_diffusion_ros.zones.area import (
    AreaUnion,
    Bounds,
    Inflated,
    OutsideBox,
    RestrictedArea,
)
from constrained_diffusion_ros.zones.episodes import EpisodeZones
from constrained_diffusion_ros.zones.geometry import (
    QUAD_SEGS,
    ZoneSet,
    rectangle,
    validate_polygon,
)
from constrained_diffusion_ros.zones.live import LiveZones, ZoneId

__all__ = [
    "QUAD_SEGS",
    "AreaUnion",
    "Bounds",
    "EpisodeZones",
    "Inflated",
    "LiveZones",
    "OutsideBox",
    "RestrictedArea",
    "ZoneId",
    "ZoneSet",
    "rectangle",
    "validate_polygon",
]
