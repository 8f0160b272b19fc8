"""Restricted areas from other packages: a check named in a scenario file, built at load time.

A user's check (a costmap, a learned model, zones in a camera image) is a `RestrictedArea`
subclass in a package of its own; a scenario names it as "package.module:Class", or by an entry
point in the group `constrained_diffusion_ros.restricted_areas` of that package's metadata, so it
works without editing this one. Whatever goes wrong while finding or building it is reported as
one ValueError line that names the spec, as every other malformed scenario is.

A scenario file is data, so naming a callable must not run it. Importing a module runs its
top-level code, so a "module:Class" spec is imported only from a module plug-ins may come from
(`allowed_module`: this package's, one that an installed distribution declares an entry point
of the group in, or one listed in the environment variable `PLUGIN_MODULES_ENV`); anything else
("this:s", which would print the Zen of Python) is refused before anything is imported. The
spec then has to resolve, without calling anything (attributes are read statically), to a
concrete `RestrictedArea` subclass before the class is called with the scenario's parameters
("os:system" is refused unrun). The built area is then asked about `probe_points` of the
workspace, in the shapes and dtypes the planner asks in, so an area that answers NaN, the wrong
shape or an exception is refused at load, not mid-plan; and what `load_area` returns checks
every answer in use too (`CheckedArea`), so a check that turns bad later (NaN after a while)
raises `ZoneCheckError`, naming the spec and the fault, where the planner or the shield asked.
"""

from __future__ import annotations

import importlib
import inspect
import math
import os
import re
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any

import torch
from torch import Tensor

from constrained_diffusion_ros.zones.area import Bounds, RestrictedArea

ENTRY_POINT_GROUP = "constrained_diffusion_ros.restricted_areas"
PLUGIN_MODULES_ENV = "CONSTRAINED_DIFFUSION_ROS_PLUGIN_MODULES"  # more modules, comma-separated
OWN_PACKAGE = __name__.partition(".")[0]
PUSHT_WORKSPACE: Bounds = (0.0, 0.0, 512.0, 512.0)  # the core may not import pusht: the default
PROBE_OUTSIDE = 16.0  # px beyond each wall: the planner asks about points off the workspace too
PROBE_BATCH = (5, 6)  # the probe points again as a batch (B, H, 2), as the shield asks


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _static_attribute(target: Any, attribute: str) -> Any:
    """The dotted `attribute` of `target` (a module), read without running anything: no module
    `__getattr__`, property or other descriptor is called. AttributeError if one is missing."""
    for name in attribute.split("."):
        target = inspect.getattr_static(target, name)
    return target


def allowed_module(name: str) -> bool:
    """Whether a "module:Class" spec may import module `name`: one of this package's, one an
    installed distribution names in an entry point of `ENTRY_POINT_GROUP` (it declared itself a
    plug-in's home), or one in `$PLUGIN_MODULES_ENV` (comma-separated; a package listed allows
    its submodules). Decided on the name alone: finding a module imports its parents."""
    listed = re.split(r"[,\s]+", os.environ.get(PLUGIN_MODULES_ENV, ""))
    if any(name == root or name.startswith(f"{root}.")
           for root in (OWN_PACKAGE, *filter(None, listed))):
        return True
    return any(entry.module == name for entry in entry_points(group=ENTRY_POINT_GROUP))


def _resolve(spec: str) -> Any:
    """The object that "module:attribute" or an entry point's name refers to; nothing called,
    and a module imported only if `allowed_module`."""
    if ":" in spec:
        module_name, _, attribute = spec.partition(":")
        if not module_name or not attribute:
            raise ValueError(f"restricted area {spec!r}: expected 'package.module:Class'")
        if not allowed_module(module_name):
            raise ValueError(f"restricted area {spec!r}: module {module_name!r} is not one "
                             f"plug-ins may come from, so it was not imported (allowed: "
                             f"{OWN_PACKAGE}, modules named by entry points in "
                             f"{ENTRY_POINT_GROUP}, and those listed in ${PLUGIN_MODULES_ENV})")
        try:
            module: Any = importlib.import_module(module_name)
        except Exception as error:  # not found, or failing while it runs: one line
            raise ValueError(f"restricted area {spec!r}: cannot import {module_name!r} "
                             f"({_one_line(error)})") from error
        try:
            return _static_attribute(module, attribute)
        except AttributeError:
            raise ValueError(f"restricted area {spec!r}: module {module_name!r} has no "
                             f"attribute {attribute!r}") from None
    found = entry_points(group=ENTRY_POINT_GROUP, name=spec)
    if not found:
        known = sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
        raise ValueError(f"restricted area {spec!r}: not 'package.module:Class' and no entry "
                         f"point of that name in {ENTRY_POINT_GROUP} (known: "
                         f"{', '.join(known) or 'none'})")
    entry = next(iter(found))
    try:  # as entry.load(), but reading the attribute statically
        if not entry.attr:
            raise AttributeError("names a module, not a class")
        return _static_attribute(importlib.import_module(entry.module), entry.attr)
    except Exception as error:  # anything an import can raise: one line naming the spec
        raise ValueError(f"restricted area {spec!r}: entry point {entry.value!r} does not load "
                         f"({_one_line(error)})") from error


def _check_class(spec: str, target: Any) -> type[RestrictedArea]:
    """`target` if it is a concrete RestrictedArea subclass; refused before anything is called,
    so a spec naming a function ("os:system") or another class never runs it."""
    is_class = issubclass(type(target), type)  # isinstance(target, type), minus __class__
    if not (is_class and issubclass(target, RestrictedArea)):
        what = f"class {target.__qualname__}" if is_class else f"a {type(target).__name__}"
        raise ValueError(f"restricted area {spec!r}: names {what}, not a RestrictedArea "
                         f"subclass (subclass constrained_diffusion_ros.zones.RestrictedArea "
                         f"and implement signed_distance)")
    if inspect.isabstract(target):
        missing = ", ".join(sorted(getattr(target, "__abstractmethods__", ())))
        raise ValueError(f"restricted area {spec!r}: {target.__qualname__} is abstract "
                         f"(implement {missing})")
    return target


def probe_points(workspace: Bounds = PUSHT_WORKSPACE) -> Tensor:
    """(30, 2) float64: a 5 x 5 grid over the workspace (walls and corners included), one point
    off the grid inside it, and one `PROBE_OUTSIDE` px beyond the middle of each wall."""
    x_min, y_min, x_max, y_max = map(float, workspace)
    xs, ys = torch.linspace(x_min, x_max, 5, dtype=torch.float64), torch.linspace(
        y_min, y_max, 5, dtype=torch.float64)
    grid = torch.cartesian_prod(xs, ys)
    cx, cy, w, h = (x_min + x_max) / 2, (y_min + y_max) / 2, x_max - x_min, y_max - y_min
    extra = torch.tensor([[x_min + 0.3 * w, y_min + 0.7 * h],
                          [x_min - PROBE_OUTSIDE, cy], [x_max + PROBE_OUTSIDE, cy],
                          [cx, y_min - PROBE_OUTSIDE], [cx, y_max + PROBE_OUTSIDE]],
                         dtype=torch.float64)
    return torch.cat([grid, extra])


def _check_answers(spec: str, area: RestrictedArea, workspace: Bounds) -> None:
    """Ask `area` about the probe points as (N, 2) and as a batch (B, H, 2), in float64 and
    float32 (the planner asks in both); refuse an exception, a non-tensor, a wrong shape or
    dtype, and a NaN or -inf distance. +inf is an answer: an empty ZoneSet is +inf everywhere."""
    base = probe_points(workspace)
    for dtype in (torch.float64, torch.float32):
        for shape in ((len(base), 2), (*PROBE_BATCH, 2)):
            points = base.to(dtype).reshape(shape)
            where = f"{dtype} points of shape {tuple(shape)}"
            for method, kind in (("signed_distance", "float"), ("contains", "bool")):
                try:
                    answer = getattr(area, method)(points.clone())
                except Exception as error:  # a user's class may fail any way: one line
                    raise ValueError(f"restricted area {spec!r}: {method} failed on {where} "
                                     f"({_one_line(error)})") from error
                fault = _answer_fault(method, kind, answer, points, where)
                if fault:
                    raise ValueError(f"restricted area {spec!r}: {fault}")


def _answer_fault(method: str, kind: str, answer: Any, points: Tensor, where: str) -> str | None:
    """What is wrong with `answer`, `method`'s ("float": a distance, "bool") to `points`
    (`where` says what they were), in words starting with `method`; None if nothing."""
    if not isinstance(answer, Tensor):
        return f"{method} returned a {type(answer).__name__}, not a torch.Tensor, for {where}"
    if tuple(answer.shape) != tuple(points.shape[:-1]):
        return (f"{method} returned shape {tuple(answer.shape)} for {where}, expected "
                f"{tuple(points.shape[:-1])}")
    if kind == "bool" and answer.dtype != torch.bool:
        return f"{method} returned dtype {answer.dtype} for {where}, expected torch.bool"
    if kind == "float":
        if not answer.is_floating_point():
            return (f"{method} returned dtype {answer.dtype} for {where}, expected a "
                    f"floating-point tensor")
        bad = torch.isnan(answer) | torch.isneginf(answer)
        if bad.any():
            index = tuple(int(i) for i in torch.nonzero(bad)[0])
            x, y = (float(v) for v in points[index])
            value = "NaN" if torch.isnan(answer[index]) else "-inf"
            return f"{method} returned {value} at ({x:g}, {y:g}) for {where}"
    return None


class ZoneCheckError(RuntimeError):
    """A plug-in zone check failed in use, where the load probe had found it sound: it raised,
    or answered a NaN or -inf distance, a wrong shape or type. Where the zones are cannot be
    told, so nothing planned or guarded with them may go out."""


class CheckedArea(RestrictedArea):
    """A plug-in's area (`plugin`, named `spec` in the scenario or parameters) whose every
    answer is checked as the load probe checks it, so that a check that turns bad in use (NaN
    after a while, an exception) raises `ZoneCheckError` naming the spec and the fault.

    Unchecked, a NaN distance compares false everywhere: the hooks and the shield would take
    the zone for absent, or plan NaN waypoints that hold the pusher without a word why. What
    the plug-in's class overrides is asked of it (and what it derives, checked in turn); the
    rest is derived from the checked distance, as for any area. Its other attributes (a
    camera's `polygons`) read through."""

    def __init__(self, plugin: RestrictedArea, spec: str) -> None:
        self.plugin, self.spec = plugin, spec

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in ("plugin", "spec"):  # unpickling: not set yet
            raise AttributeError(name)
        return getattr(self.plugin, name)

    def __repr__(self) -> str:
        return f"{self.spec} ({self.plugin!r})"

    def signed_distance(self, points: Tensor) -> Tensor:
        answer = self._ask("signed_distance", points)
        if not (isinstance(answer, Tensor) and answer.is_floating_point()
                and answer.shape == points.shape[:-1] and bool((answer > -math.inf).all())):
            self._refuse("signed_distance", "float", answer, points)
        return answer

    def contains(self, points: Tensor) -> Tensor:
        if not self._own("contains"):
            return super().contains(points)
        answer = self._ask("contains", points)
        if not (isinstance(answer, Tensor) and answer.dtype == torch.bool
                and answer.shape == points.shape[:-1]):
            self._refuse("contains", "bool", answer, points)
        return answer

    def outward_direction(self, points: Tensor) -> Tensor:
        if not self._own("outward_direction"):
            return super().outward_direction(points)
        return self._finite("outward_direction", points)

    def inside_and_outward(self, points: Tensor) -> tuple[Tensor, Tensor | None]:
        if not self._own("inside_and_outward"):
            return super().inside_and_outward(points)
        return self._finite("inside_and_outward", points)

    def project_out(self, points: Tensor, margin: float = 0.0) -> Tensor:
        if not self._own("project_out"):
            return super().project_out(points, margin)
        return self._finite("project_out", points, margin)

    def segment_clear_fraction(self, starts: Tensor, ends: Tensor) -> Tensor:
        if not self._own("segment_clear_fraction"):
            return super().segment_clear_fraction(starts, ends)
        return self._finite("segment_clear_fraction", starts, ends)

    def crosses(self, starts: Tensor, ends: Tensor) -> Tensor:
        if not self._own("crosses"):
            return super().crosses(starts, ends)
        return self._finite("crosses", starts, ends)

    def select_rows(self, rows: Tensor) -> RestrictedArea:
        return self._derive(self._ask("select_rows", rows)) if self._own("select_rows") \
            else self

    def near(self, points: Tensor, reach: float) -> RestrictedArea:
        return self._derive(self._ask("near", points, reach)) if self._own("near") else self

    def _inflated(self, radius: float) -> RestrictedArea:
        if self._own("_inflated") or self._own("inflate"):
            return self._derive(self._ask("inflate", radius))
        return super()._inflated(radius)

    def _bounded(self, workspace: Bounds) -> RestrictedArea:
        if self._own("_bounded") or self._own("bounded"):
            return self._derive(self._ask("bounded", workspace))
        return super()._bounded(workspace)

    def _own(self, method: str) -> bool:
        """The plug-in's class overrides RestrictedArea's `method`."""
        return getattr(type(self.plugin), method) is not getattr(RestrictedArea, method)

    def _ask(self, method: str, *args: Any) -> Any:
        try:
            return getattr(self.plugin, method)(*args)
        except ZoneCheckError:
            raise
        except Exception as error:  # a user's class may fail any way: one line
            raise ZoneCheckError(f"zone check {self.spec!r}: {method} failed "
                                 f"({_one_line(error)})") from error

    def _refuse(self, method: str, kind: str, answer: Any, points: Tensor) -> None:
        where = f"{getattr(points, 'dtype', type(points).__name__)} points of shape " \
                f"{tuple(points.shape)}"
        fault = _answer_fault(method, kind, answer, points, where)
        raise ZoneCheckError(f"zone check {self.spec!r}: {fault or method + ' failed'}")

    def _finite(self, method: str, *args: Any) -> Any:
        """What the plug-in's own `method` answers: tensors, each boolean or finite."""
        answer = self._ask(method, *args)
        for part in answer if isinstance(answer, tuple) else (answer,):
            if part is None or (isinstance(part, Tensor) and (
                    part.dtype == torch.bool or bool(torch.isfinite(part).all()))):
                continue
            what = "a non-finite tensor" if isinstance(part, Tensor) else \
                f"a {type(part).__name__}"
            raise ZoneCheckError(f"zone check {self.spec!r}: {method} returned {what}")
        return answer

    def _derive(self, area: Any) -> RestrictedArea:
        if area is self.plugin:
            return self
        if not isinstance(area, RestrictedArea):
            raise ZoneCheckError(f"zone check {self.spec!r}: derived a {type(area).__name__}, "
                                 f"not a RestrictedArea")
        return CheckedArea(area, self.spec)


def load_area(spec: str, parameters: Mapping[str, Any] | None = None, *,
              workspace: Bounds = PUSHT_WORKSPACE) -> CheckedArea:
    """Build the restricted area `spec` names, calling it with `parameters` as keywords.

    `spec` is "package.module:Class" (a dotted attribute path after the colon works too), its
    module one `allowed_module` allows, or the name of an entry point in `ENTRY_POINT_GROUP`;
    either must name a concrete `RestrictedArea` subclass, checked before anything is called.
    The built area is probed on `probe_points` of `workspace` (px). Raises ValueError, naming
    the spec, for a module not allowed (before importing it), a missing module or attribute,
    anything but such a class, parameters the class refuses (TypeError) or any other failure
    to build it, and an answer on the probe points that is not a finite (or +inf) distance.
    The area comes as a `CheckedArea`: an answer as bad in use raises `ZoneCheckError`.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"restricted area spec must be a non-empty string, got {spec!r}")
    spec = spec.strip()
    parameters = {} if parameters is None else parameters
    if not isinstance(parameters, Mapping) or not all(isinstance(k, str) for k in parameters):
        raise ValueError(f"restricted area {spec!r}: parameters must be a mapping of names to "
                         f"values, got {parameters!r}")
    cls = _check_class(spec, _resolve(spec))
    try:
        area = cls(**parameters)
    except TypeError as error:
        raise ValueError(f"restricted area {spec!r}: bad parameters {sorted(parameters)} "
                         f"({_one_line(error)})") from error
    except Exception as error:  # a user's class may fail any way: one line naming the spec
        raise ValueError(f"restricted area {spec!r}: cannot be built "
                         f"({_one_line(error)})") from error
    if not isinstance(area, RestrictedArea):  # a __new__ may return anything
        raise ValueError(f"restricted area {spec!r}: built a {type(area).__name__}, not a "
                         f"RestrictedArea (subclass constrained_diffusion_ros.zones."
                         f"RestrictedArea and implement signed_distance)")
    _check_answers(spec, area, workspace)
    return CheckedArea(area, spec)
