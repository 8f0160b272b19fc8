"""Constraint configurations: which hooks run inside the denoising loop, how strongly, under
which sampler, and whether the shield has the last word. Read from `config/configurations.yaml`
by the policy node and the evaluation alike; how a report labels them is the evaluation's."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import yaml

from constrained_diffusion_ros.policy.schedulers import SPACINGS


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


# Field annotation -> (check, what it must be): the one table the type check reads.
FIELD_KINDS = {
    "bool": (lambda v: isinstance(v, bool), "true or false"),
    "str": (lambda v: isinstance(v, str), "text"),
    "float": (lambda v: _number(v) and math.isfinite(v), "a finite number"),
    "int": (lambda v: _number(v) and isinstance(v, int), "an integer"),
    "int | None": (lambda v: v is None or (_number(v) and isinstance(v, int)), "an integer"),
}


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
    repair_from: float = 1.0  # path repair after every update from this progress (0..1) on;
    # 1: after the last only
    guide_until: float = 1.0  # resampling and push only up to this progress (0..1)
    margin_shrink: float = 0.0  # px: resampling and push see the zones grown by this much
    # more at the first update, shrinking to nothing at the last
    shield: bool = False  # keep the pusher's predicted path (its disc) out, setpoint by setpoint
    from_scratch: int = 0  # >0: no hooks; draw this many whole chunks, keep the first that fits
    candidates: int = 1  # >1: this many steered chunks per episode; keep the one the final
    # projection and path repair moved least
    sampler: str = "ddpm"
    denoising_steps: int | None = None
    timestep_spacing: str = "leading"  # which training timesteps a shorter schedule visits
    eta: float = 0.0  # DDIM: 0 deterministic given the first noise, 1 DDPM-like

    def __post_init__(self) -> None:
        for spec in fields(self):  # types as written in a YAML file: say which field is wrong
            check, text = FIELD_KINDS[spec.type]
            value = getattr(self, spec.name)
            if not check(value):
                raise ValueError(f"configuration {self.name!r}: {spec.name} must be {text}, "
                                 f"got {value!r}")
        if self.denoising_steps is not None and self.denoising_steps < 1:
            raise ValueError(f"configuration {self.name!r}: denoising_steps must be at least "
                             f"1 (or left out: the training schedule's)")
        if self.candidates < 1:
            raise ValueError(f"configuration {self.name!r}: candidates must be at least 1")
        if self.from_scratch and self.candidates > 1:
            raise ValueError(f"configuration {self.name!r}: from_scratch draws its own "
                             f"candidates")
        if min(self.push, self.margin, self.from_scratch, self.margin_shrink) < 0:
            raise ValueError(f"configuration {self.name!r}: push, margin, margin_shrink and "
                             "from_scratch must be non-negative")
        if self.from_scratch and (self.resample or self.push or self.path_repair):
            raise ValueError(f"configuration {self.name!r}: from_scratch replaces the hooks")
        if self.sampler not in ("ddpm", "ddim"):
            raise ValueError(f"configuration {self.name!r}: sampler must be ddpm or ddim")
        if self.timestep_spacing not in SPACINGS:
            raise ValueError(f"configuration {self.name!r}: timestep_spacing must be one of "
                             f"{', '.join(SPACINGS)}")
        for name in ("eta", "repair_from", "guide_until"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"configuration {self.name!r}: {name} must be in [0, 1]")

    @property
    def constrains(self) -> bool:
        """Whether the zones change what it plans (the "None" rows ignore them)."""
        return bool(self.resample or self.push or self.project or self.path_repair
                    or self.from_scratch or self.shield)

    @property
    def sampler_key(self) -> tuple:
        """Configurations with equal keys can share one batch of network calls."""
        return (self.sampler, self.denoising_steps, self.timestep_spacing, self.eta,
                (self.from_scratch or self.candidates > 1) and self.name)


def read_yaml(path: str | Path) -> object:
    """A YAML file, safe-loaded (no tags that run code); any fault is one ValueError line
    naming the file and, for a syntax error, where it is."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ValueError(f"{path}: not valid YAML{where}: {error.problem}") from None
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not valid YAML: {' '.join(str(error).split())}") from None


def load_configurations(path: str | Path) -> dict[str, ConstraintConfig]:
    """Reads `name: {field: value}` entries; unknown fields are refused by name."""
    path = Path(path)
    document = read_yaml(path) or {}
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
