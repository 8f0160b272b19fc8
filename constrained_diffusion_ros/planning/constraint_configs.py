"""Constraint configurations: which hooks run inside the denoising loop, how strongly, under
which sampler, and whether the shield has the last word. Read from `config/configurations.yaml`
by the policy node and the evaluation alike; how a report labels them is the evaluation's."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import yaml
from yaml.composer import ComposerError

from constrained_diffusion_ros.policy.policy_config import read_text_file
from constrained_diffusion_ros.policy.schedulers import SPACINGS

# Upper bounds that keep a typo from planning for minutes or allocating gigabytes, far above
# what anyone runs: DDPM's own schedule has 1000 steps (the shipped ones 100 and 10), and each
# candidate or from-scratch chunk is one more row of every network call (shipped: 8).
MAX_DENOISING_STEPS = 1000
MAX_CHUNKS = 1024  # candidates and from_scratch
# YAML: the shipped files are a few kB and their aliases add 119 nodes; these bounds are
# generous by far, yet an alias bomb of a few hundred bytes (nine levels of nine aliases: 387
# million nodes, gigabytes once expanded) is refused as soon as its aliases pass the budget.
MAX_YAML_BYTES = 4 << 20
ALIAS_NODE_BUDGET = 10_000  # nodes that aliases may add to a document, all aliases together


GUARANTEES = ("none", "setpoint", "body")  # what a configuration promises, weakest first


def weakens(before: ConstraintConfig, after: ConstraintConfig) -> bool:
    """Whether `after` promises less of a setpoint than `before` (`guarantee`)."""
    return GUARANTEES.index(after.guarantee) < GUARANTEES.index(before.guarantee)


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
    slide: bool = True  # shield and path repair: the nearest safe point (around a zone); false:
    # the largest safe step along the blocked line (stops in front of it)
    from_scratch: int = 0  # >0: no hooks; draw this many whole chunks, keep the first that fits
    candidates: int = 1  # >1: this many steered chunks per episode; keep the one the final
    # projection and path repair moved least
    sampler: str = "ddpm"
    denoising_steps: int | None = None
    timestep_spacing: str = "leading"  # which training timesteps a shorter schedule visits
    eta: float = 0.0  # DDIM: 0 deterministic given the first noise, 1 DDPM-like
    zone_guidance: float = 1.0  # a zone-aware policy: its noise is the blind one plus this
    # times the difference the zones make (classifier-free guidance); 1: with the zones alone

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
        if self.denoising_steps is not None and self.denoising_steps > MAX_DENOISING_STEPS:
            raise ValueError(f"configuration {self.name!r}: denoising_steps must be at most "
                             f"{MAX_DENOISING_STEPS}, got {self.denoising_steps}")
        if self.candidates < 1:
            raise ValueError(f"configuration {self.name!r}: candidates must be at least 1")
        for name in ("candidates", "from_scratch"):
            if getattr(self, name) > MAX_CHUNKS:
                raise ValueError(f"configuration {self.name!r}: {name} must be at most "
                                 f"{MAX_CHUNKS}, got {getattr(self, name)}")
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
        if self.zone_guidance < 0:
            raise ValueError(f"configuration {self.name!r}: zone_guidance must be "
                             f"non-negative")
        for name in ("eta", "repair_from", "guide_until"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"configuration {self.name!r}: {name} must be in [0, 1]")

    @property
    def constrains(self) -> bool:
        """Whether the zones change what it plans (the "None" rows ignore them)."""
        return bool(self.resample or self.push or self.project or self.path_repair
                    or self.from_scratch or self.shield)

    @property
    def guarantee(self) -> str:
        """What it promises of every setpoint, weakest first in GUARANTEES: "body" (the
        pusher's predicted disc kept out: shield on zones grown by its radius), "setpoint" (no
        commanded setpoint inside a zone: the final projection), or "none" (guidance at most)."""
        if self.shield and self.inflate:
            return "body"
        return "setpoint" if self.project or self.shield else "none"

    @property
    def sampler_key(self) -> tuple:
        """Configurations with equal keys can share one batch of network calls."""
        return (self.sampler, self.denoising_steps, self.timestep_spacing, self.eta,
                self.zone_guidance, (self.from_scratch or self.candidates > 1) and self.name)


class BoundedSafeLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader (no tags that run code) that also refuses an alias to a node still
    being read (a cycle) and aliases that together add more than ALIAS_NODE_BUDGET nodes: an
    alias costs nothing to read but its copies are all walked by whoever prints or checks the
    document (a billion-laughs file). Counted while composing, before anything is built."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._sizes: dict[int, int] = {}  # id(node) -> its node count with aliases expanded
        self._open: set[str] = set()  # anchors of the collections being read
        self._added = 0  # nodes the aliases read so far add

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node:
        event = self.peek_event()
        anchor = getattr(event, "anchor", None)
        if isinstance(event, yaml.AliasEvent):
            if anchor in self._open:
                raise ComposerError(None, None, f"alias *{anchor} refers to the node it is in",
                                    event.start_mark)
            node = super().compose_node(parent, index)
            self._added += self._size(node)
            if self._added > ALIAS_NODE_BUDGET:
                raise ComposerError(
                    None, None, f"aliases expand to more than {ALIAS_NODE_BUDGET} nodes "
                    f"(an alias bomb?)", event.start_mark)
            return node
        if anchor is None or isinstance(event, yaml.ScalarEvent):
            return super().compose_node(parent, index)
        self._open.add(anchor)
        try:
            return super().compose_node(parent, index)
        finally:
            self._open.discard(anchor)

    def _size(self, node: yaml.Node) -> int:
        """Nodes in `node` with every alias expanded, each node counted once per path (so
        shared anchors are summed, not walked: nine levels of nine cost 81 look-ups)."""
        known = self._sizes.get(id(node))
        if known is None:
            if isinstance(node, yaml.SequenceNode):
                known = 1 + sum(self._size(child) for child in node.value)
            elif isinstance(node, yaml.MappingNode):
                known = 1 + sum(self._size(k) + self._size(v) for k, v in node.value)
            else:
                known = 1
            self._sizes[id(node)] = known
        return known


def safe_yaml(text: str, where: str) -> object:
    """`text` (from `where`: a file, a parameter) as YAML, safely (no tags that run code, no
    alias bombs, see BoundedSafeLoader); any fault is one ValueError line naming `where` and,
    for a syntax error, the line. The one YAML reader of the package's own files and text."""
    try:
        return yaml.load(text, Loader=BoundedSafeLoader)  # a SafeLoader: no code runs
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ValueError(f"{where}: not valid YAML{at}: {error.problem}") from None
    except yaml.YAMLError as error:
        raise ValueError(f"{where}: not valid YAML: {' '.join(str(error).split())}") from None
    except RecursionError:  # "[[[[..." nested past the parser's stack
        raise ValueError(f"{where}: not valid YAML: nested too deeply") from None


def read_yaml(path: str | Path) -> object:
    """A YAML file, read as `safe_yaml` reads text; it must be a regular file (a FIFO would
    block) of at most MAX_YAML_BYTES. Any fault is one ValueError line naming the file."""
    return safe_yaml(read_text_file(path, MAX_YAML_BYTES), str(path))


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
