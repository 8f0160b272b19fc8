"""Restricted-zone scenarios read from `config/scenarios.yaml`: the one home of every scenario,
used by the evaluation, the zone publisher node and the trial command alike.

A scenario's zones are polygons: drawn (rectangle, square, polygon) or the exact outline of a
keep-out grid (`grid`, see `zones.grid`). Or, instead of zones, a `plugin`: any
`RestrictedArea` built by `zones.plugins.load_area`, which the evaluation queries as it is;
its polygons (for drawing and for the zone topic) are those it offers as `polygons`, if any.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path

import numpy as np
import shapely

from constrained_diffusion_ros.evaluation.zone_paths import ZonePath
from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.planning.constraint_configs import read_yaml
from constrained_diffusion_ros.pusht import PUSHT_ROBOT
from constrained_diffusion_ros.zones.area import RestrictedArea
from constrained_diffusion_ros.zones.geometry import ZoneSet, rectangle, validate_polygon
from constrained_diffusion_ros.zones.grid import (
    DEFAULT_THRESHOLD,
    grid_polygons,
    rasterize,
    read_pgm,
)
from constrained_diffusion_ros.zones.plugins import load_area

GRID_KEYS = {"from_scenario", "file", "resolution", "origin", "threshold", "negate"}


def polygon_from_spec(spec: dict, where: str) -> np.ndarray:
    """One zone entry (rectangle / square / polygon) -> (V, 2) vertices, validated."""
    if not isinstance(spec, dict) or len(spec) != 1:
        raise ValueError(f"{where}: a zone is one of rectangle, square or polygon")
    (kind, value), = spec.items()
    try:
        if kind == "rectangle":
            vertices = rectangle(*map(float, value))
        elif kind == "square":
            (cx, cy), half = map(float, value["center"]), float(value["side"]) / 2
            vertices = rectangle(cx - half, cy - half, cx + half, cy + half)
        elif kind == "polygon":
            vertices = np.asarray(value, dtype=float)
        else:
            raise ValueError(f"unknown zone kind {kind!r}")
    except (TypeError, KeyError) as error:
        raise ValueError(f"{where}: malformed {kind}: {error}") from error
    validate_polygon(vertices, where)
    return np.asarray(vertices, dtype=float)


def grid_from_spec(spec: object, where: str, directory: Path,
                   defined: dict[str, Scenario]) -> list[np.ndarray]:
    """A `grid` zone entry -> the exact polygons of its keep-out cells, within the workspace.

    The mask is `from_scenario` (the zones of a scenario defined above, rasterized over the
    workspace by cell centres) or `file` (a binary PGM, relative to the scenarios file), with
    cells of `resolution` px from `origin` [x, y] (default [0, 0]), keep-out from `threshold`.
    """
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: grid must be a mapping, e.g. {{from_scenario: center_0.2, "
                         f"resolution: 4}}")
    unknown = sorted(set(spec) - GRID_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown grid keys {unknown}; known: {sorted(GRID_KEYS)}")
    if ("from_scenario" in spec) == ("file" in spec):
        raise ValueError(f"{where}: a grid has exactly one of from_scenario and file")
    try:
        resolution = float(spec["resolution"])
        origin = tuple(map(float, spec.get("origin", (0.0, 0.0))))
        threshold = int(spec.get("threshold", DEFAULT_THRESHOLD))
        if len(origin) != 2 or not math.isfinite(resolution) or resolution <= 0:
            raise ValueError("origin must be [x, y] and resolution a positive number")
        *_, x_max, y_max = PUSHT_ROBOT.workspace
        if "from_scenario" in spec:
            source = defined.get(spec["from_scenario"])
            if source is None or not source.polygons:
                raise ValueError(f"from_scenario {spec['from_scenario']!r} is no scenario with "
                                 f"polygons defined above this one")
            width = max(0, math.ceil((x_max - origin[0]) / resolution))
            height = max(0, math.ceil((y_max - origin[1]) / resolution))
            values = rasterize(source.polygons, resolution, origin, width, height)
        else:
            values = read_pgm(directory / str(spec["file"]), bool(spec.get("negate", False)))
        polygons = grid_polygons(values, resolution, origin, threshold,
                                 workspace=PUSHT_ROBOT.workspace)
    except KeyError as error:
        raise ValueError(f"{where}: grid lacks {error}") from None
    except (TypeError, ValueError, OSError) as error:
        raise ValueError(f"{where}: {error}") from error
    if not polygons:
        raise ValueError(f"{where}: the grid has no keep-out cell inside the workspace")
    return polygons


def plugin_from_spec(spec: object, where: str) -> RestrictedArea:
    """A `plugin` entry {class, parameters} -> the area `zones.plugins.load_area` builds."""
    if not isinstance(spec, dict) or "class" not in spec or set(spec) - {"class", "parameters"}:
        raise ValueError(f"{where}: plugin is {{class: 'package.module:Class' or an entry "
                         f"point name, parameters: {{...}}}}")
    try:
        return load_area(spec["class"], spec.get("parameters") or {},
                         workspace=PUSHT_ROBOT.workspace)
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None


@dataclass(frozen=True, eq=False)  # identity hash: zone sets are cached per scenario
class Scenario:
    name: str
    label: str
    polygons: tuple[np.ndarray, ...]  # what is drawn and published; the zones unless `area`
    paper: bool = False
    motion: ZonePath | None = None  # how the zones move (None: they stand still)
    area: RestrictedArea | None = None  # a plug-in area (static), answering for the zones
    plugin: dict | None = None  # its spec {class, parameters}, for a node to load it too

    @property
    def moving(self) -> bool:
        return self.motion is not None

    @property
    def homes(self) -> bool:
        """Its zones head for the pusher: where they are depends on the episode."""
        return self.motion is not None and self.motion.homes

    @property
    def centroid(self) -> np.ndarray:
        """(2,) the drawn zones' centroid: what a homing zone steers toward the pusher."""
        return shapely.get_coordinates(_zone_set(self, 0).geometry.centroid)[0]

    def offset_at(self, step: int) -> np.ndarray:
        """(2,) px the zones are moved by at a control step (a homing one: along its path,
        without the homing, which `ZoneMover` adds per episode)."""
        if not self.moving:
            return np.zeros(2)
        return self.motion.offset_at(step / PUSHT_ROBOT.control_hz)

    def polygons_at(self, step: int, offset: np.ndarray | None = None) -> list[np.ndarray]:
        """The zones in force at a control step (moved by `offset` instead, if given)."""
        offset = self.offset_at(step) if offset is None else offset
        return [p + offset for p in self.polygons]

    def zones_at(self, step: int) -> RestrictedArea:
        """The area in force at a control step: the plug-in's own, else the polygons' union."""
        if self.area is not None:
            return self.area
        return _zone_set(self, step if self.moving else 0)


@cache
def _zone_set(scenario: Scenario, step: int) -> ZoneSet:
    return ZoneSet.from_polygons(scenario.polygons_at(step))


def _zone_polygons(zones: list, where: str, directory: Path,
                   defined: dict[str, Scenario]) -> tuple[np.ndarray, ...]:
    polygons: list[np.ndarray] = []
    for i, zone in enumerate(zones):
        if isinstance(zone, dict) and set(zone) == {"grid"}:
            polygons += grid_from_spec(zone["grid"], f"{where} zone {i}", directory, defined)
        else:
            polygons.append(polygon_from_spec(zone, f"{where} zone {i}"))
    return tuple(polygons)


def load_scenarios(path: str | Path | None = None) -> dict[str, Scenario]:
    path = Path(path) if path else config_dir() / "scenarios.yaml"
    document = read_yaml(path) or {}
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected a mapping of scenario names to zones")
    scenarios: dict[str, Scenario] = {}
    for name, entry in document.items():
        where = f"{path.name}: scenario {name!r}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where} must be a mapping (label, zones or plugin, motion)")
        zones, plugin, motion = entry.get("zones") or [], entry.get("plugin"), entry.get("motion")
        if zones and plugin:
            raise ValueError(f"{where} has both zones and a plugin; give one")
        if plugin and motion:
            raise ValueError(f"{where}: a plugin area does not move (no motion)")
        area = plugin_from_spec(plugin, f"{where} plugin") if plugin else None
        if area is not None:
            polygons = tuple(np.asarray(p, dtype=float) for p in getattr(area, "polygons", ()))
        elif zones:
            polygons = _zone_polygons(zones, where, path.parent, scenarios)
        else:
            raise ValueError(f"{where} has no zones")
        try:
            speeds = [float(v) for v in (motion or {}).get("speeds", [])]
            zone_path = ZonePath.from_spec(motion) if motion and not speeds else None
            variants = [ZonePath.from_spec(motion, speed) for speed in speeds]
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where} motion: {error}") from None
        scenario = Scenario(
            name=name, label=str(entry.get("label", name)), polygons=polygons,
            paper=bool(entry.get("paper", False)), motion=zone_path, area=area,
            plugin=dict(plugin) if plugin else None)
        if not variants:
            scenarios[name] = scenario
        for speed, variant in zip(speeds, variants):  # name@speed, one per speed
            scenarios[f"{name}@{speed:g}"] = replace(
                scenario, name=f"{name}@{speed:g}", label=f"{scenario.label}, {speed:g} px/s",
                motion=variant)
    return scenarios
