"""The evaluation's view of the constraint configurations: how the report labels each one,
whether it is one of the paper's six, and on which scenarios it runs (`config/evaluation.yaml`).
What a configuration does is `planning.constraint_configs`'s; this is presentation only."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from constrained_diffusion_ros.planning.constraint_configs import (
    ConstraintConfig,
    load_configurations,
    read_yaml,
)

SCENARIO_CHOICES = ("all", "paper")


@dataclass(frozen=True)
class EvaluatedConfiguration:
    """A configuration as a column of the report."""

    config: ConstraintConfig
    label: str
    paper: bool = False  # one of the paper's six configurations
    scenarios: str = "all"  # evaluate on "all" scenarios or only the "paper" ones

    @property
    def name(self) -> str:
        return self.config.name


def load_evaluated(config_dir: str | Path) -> dict[str, EvaluatedConfiguration]:
    """Every configuration of `configurations.yaml`, with the labels of `evaluation.yaml`."""
    directory = Path(config_dir)
    configs = load_configurations(directory / "configurations.yaml")
    path = directory / "evaluation.yaml"
    # Absent: every configuration under its own name. Present, it must be a regular file:
    # read_yaml refuses a FIFO, a directory or a dangling link in one line.
    present = path.exists() or path.is_symlink()
    document = (read_yaml(path) if present else None) or {}
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected a mapping of configuration names to labels")
    unknown = sorted(set(document) - set(configs))
    if unknown:
        raise ValueError(f"{path}: no configuration named {unknown} in configurations.yaml")
    evaluated = {}
    for name, config in configs.items():
        entry = dict(document.get(name) or {})
        extra = sorted(set(entry) - {"label", "paper", "scenarios"})
        if extra:
            raise ValueError(f"{path}: {name!r} has unknown keys {extra}")
        scenarios = entry.get("scenarios", "all")
        if scenarios not in SCENARIO_CHOICES:
            raise ValueError(f"{path}: {name!r}: scenarios must be all or paper")
        evaluated[name] = EvaluatedConfiguration(config, str(entry.get("label", name)),
                                                 bool(entry.get("paper", False)), scenarios)
    return evaluated
