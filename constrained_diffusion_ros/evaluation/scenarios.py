"""Restricted-zone scenarios read from `config/scenarios.yaml`: the one home of every scenario,
used by the evaluation, the zone publisher node and the trial command alike."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import yaml

from constrained_diffusion_ros.paths import config_dir
from constrained_diffusion_ros.zones.geometry import ZoneSet, rectangle, validate_polygon


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


@dataclass(frozen=True, eq=False)  # identity hash: zone sets are cached per scenario
class Scenario:
    name: str
    label: str
    polygons: tuple[np.ndarray, ...]
    paper: bool = False
    motion_offset: tuple[float, float] | None = None  # total translation (px)
    motion_steps: int = 1

    @property
    def moving(self) -> bool:
        return self.motion_offset is not None

    def offset_at(self, step: int) -> np.ndarray:
        if not self.moving:
            return np.zeros(2)
        return np.asarray(self.motion_offset) * min(1.0, step / self.motion_steps)

    def polygons_at(self, step: int) -> list[np.ndarray]:
        """The zones in force at a control step."""
        offset = self.offset_at(step)
        return [p + offset for p in self.polygons]

    def zones_at(self, step: int) -> ZoneSet:
        return _zone_set(self, step if self.moving else 0)


@cache
def _zone_set(scenario: Scenario, step: int) -> ZoneSet:
    return ZoneSet.from_polygons(scenario.polygons_at(step))


def load_scenarios(path: str | Path | None = None) -> dict[str, Scenario]:
    path = Path(path) if path else config_dir() / "scenarios.yaml"
    document = yaml.safe_load(path.read_text()) or {}
    scenarios = {}
    for name, entry in document.items():
        where = f"{path.name}: scenario {name!r}"
        zones = entry.get("zones") or []
        if not zones:
            raise ValueError(f"{where} has no zones")
        polygons = tuple(polygon_from_spec(z, f"{where} zone {i}") for i, z in enumerate(zones))
        motion = entry.get("motion")
        scenarios[name] = Scenario(
            name=name, label=str(entry.get("label", name)), polygons=polygons,
            paper=bool(entry.get("paper", False)),
            motion_offset=tuple(map(float, motion["offset"])) if motion else None,
            motion_steps=int(motion["steps"]) if motion else 1)
    return scenarios
