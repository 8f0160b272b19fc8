"""Constraint configurations: which hooks run inside the denoising loop, how strongly, under
which sampler, and whether the shield has the last word. Read from `config/configurations.yaml`
by the policy node and the evaluation alike; how a report labels them is the evaluation's."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import yaml


@dataclass(frozen=True)
class ConstraintConfig:
    """Which hooks run, with which strength, under which sampler."""

    name: str
    resample: bool = False
    push: float = 0.0  # lambda: pixels per denoising step; 0 turns the push off
    project: bool = False
    margin: float = 1.0  # clearance (px) left by projection and path repair
    inflate: bool = False  # grow zones by the pusher radius so its body stays out too
    path_repair: bool = False
    shield: bool = False  # keep the pusher's predicted path (its disc) out, setpoint by setpoint
    from_scratch: int = 0  # >0: no hooks; draw this many whole chunks, keep the first that fits
    sampler: str = "ddpm"
    denoising_steps: int | None = None

    def __post_init__(self) -> None:
        if self.push < 0 or self.margin < 0 or self.from_scratch < 0:
            raise ValueError(f"configuration {self.name!r}: push, margin and from_scratch "
                             "must be non-negative")
        if self.from_scratch and (self.resample or self.push or self.path_repair):
            raise ValueError(f"configuration {self.name!r}: from_scratch replaces the hooks")
        if self.sampler not in ("ddpm", "ddim"):
            raise ValueError(f"configuration {self.name!r}: sampler must be ddpm or ddim")

    @property
    def constrains(self) -> bool:
        """Whether the zones change what it plans (the "None" rows ignore them)."""
        return bool(self.resample or self.push or self.project or self.path_repair
                    or self.from_scratch or self.shield)

    @property
    def sampler_key(self) -> tuple:
        """Configurations with equal keys can share one batch of network calls."""
        return (self.sampler, self.denoising_steps, self.from_scratch and self.name)


def load_configurations(path: str | Path) -> dict[str, ConstraintConfig]:
    """Reads `name: {field: value}` entries; unknown fields are refused by name."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"cannot read configurations from {path}: {error}") from None
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected a mapping of configuration names to fields")
    known = {f.name for f in fields(ConstraintConfig)} - {"name"}
    configs = {}
    for name, entry in document.items():
        entry = entry or {}
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: configuration {name!r} must be a mapping of fields")
        unknown = sorted(set(entry) - known)
        if unknown:
            raise ValueError(f"{path}: configuration {name!r} has unknown keys {unknown}")
        configs[str(name)] = ConstraintConfig(name=str(name), **entry)
    return configs
