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
shape or an exception is refused at load, not mid-plan.
"""

from __future__ import annotations

import importlib
import inspect
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
                _check_answer(spec, method, kind, answer, points, where)


def _check_answer(spec: str, method: str, kind: str, answer: Any, points: Tensor,
                  where: str) -> None:
    prefix = f"restricted area {spec!r}: {method}"
    if not isinstance(answer, Tensor):
        raise ValueError(f"{prefix} returned a {type(answer).__name__}, not a torch.Tensor, "
                         f"for {where}")
    if tuple(answer.shape) != tuple(points.shape[:-1]):
        raise ValueError(f"{prefix} returned shape {tuple(answer.shape)} for {where}, expected "
                         f"{tuple(points.shape[:-1])}")
    if kind == "bool" and answer.dtype != torch.bool:
        raise ValueError(f"{prefix} returned dtype {answer.dtype} for {where}, expected "
                         f"torch.bool")
    if kind == "float":
        if not answer.is_floating_point():
            raise ValueError(f"{prefix} returned dtype {answer.dtype} for {where}, expected a "
                             f"floating-point tensor")
        bad = torch.isnan(answer) | torch.isneginf(answer)
        if bad.any():
            index = tuple(int(i) for i in torch.nonzero(bad)[0])
            x, y = (float(v) for v in points[index])
            value = "NaN" if torch.isnan(answer[index]) else "-inf"
            raise ValueError(f"{prefix} returned {value} at ({x:g}, {y:g}) for {where}")


def load_area(spec: str, parameters: Mapping[str, Any] | None = None, *,
              workspace: Bounds = PUSHT_WORKSPACE) -> RestrictedArea:
    """Build the restricted area `spec` names, calling it with `parameters` as keywords.

    `spec` is "package.module:Class" (a dotted attribute path after the colon works too), its
    module one `allowed_module` allows, or the name of an entry point in `ENTRY_POINT_GROUP`;
    either must name a concrete `RestrictedArea` subclass, checked before anything is called.
    The built area is probed on `probe_points` of `workspace` (px). Raises ValueError, naming
    the spec, for a module not allowed (before importing it), a missing module or attribute,
    anything but such a class, parameters the class refuses (TypeError) or any other failure
    to build it, and an answer on the probe points that is not a finite (or +inf) distance.
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
    return area
