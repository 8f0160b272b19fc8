"""Restricted zones: the area protocol every check implements (`area`), exact polygon unions
(`geometry`), different zones per episode of a batch (`episodes`), the live id-keyed set a
node updates from messages (`live`), keep-out grids as exact polygons (`grid`), and areas
from other packages (`plugins`; `constrained_diffusion_ros.examples.camera` is one)."""

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
from constrained_diffusion_ros.zones.grid import grid_polygons, rasterize
from constrained_diffusion_ros.zones.live import LiveZones, ZoneId
from constrained_diffusion_ros.zones.plugins import load_area

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
    "grid_polygons",
    "load_area",
    "rasterize",
    "rectangle",
    "validate_polygon",
]
