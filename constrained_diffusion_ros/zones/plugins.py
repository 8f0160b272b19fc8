"""Restricted areas from other packages: a check named in a scenario file, built at load time.

A user's check (a costmap, a learned model, zones in a camera image) is a `RestrictedArea`
subclass in a package of its own; a scenario names it as "package.module:Class", or by an entry
point in the group `constrained_diffusion_ros.restricted_areas` of that package's metadata, so it
works without editing this one. Whatever goes wrong while finding or building it is reported as
one ValueError line that names the spec, as every other malformed scenario is.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any

from constrained_diffusion_ros.zones.area import RestrictedArea

ENTRY_POINT_GROUP = "constrained_diffusion_ros.restricted_areas"


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _resolve(spec: str) -> Any:
    """The object that "module:attribute" or an entry point's name refers to."""
    if ":" in spec:
        module_name, _, attribute = spec.partition(":")
        if not module_name or not attribute:
            raise ValueError(f"restricted area {spec!r}: expected 'package.module:Class'")
        try:
            target: Any = importlib.import_module(module_name)
        except Exception as error:  # not found, or failing while it runs: one line
            raise ValueError(f"restricted area {spec!r}: cannot import {module_name!r} "
                             f"({_one_line(error)})") from error
        for name in attribute.split("."):
            if not hasattr(target, name):
                raise ValueError(f"restricted area {spec!r}: module {module_name!r} has no "
                                 f"attribute {attribute!r}")
            target = getattr(target, name)
        return target
    found = entry_points(group=ENTRY_POINT_GROUP, name=spec)
    if not found:
        known = sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
        raise ValueError(f"restricted area {spec!r}: not 'package.module:Class' and no entry "
                         f"point of that name in {ENTRY_POINT_GROUP} (known: "
                         f"{', '.join(known) or 'none'})")
    entry = next(iter(found))
    try:
        return entry.load()
    except Exception as error:  # anything an import can raise: one line naming the spec
        raise ValueError(f"restricted area {spec!r}: entry point {entry.value!r} does not load "
                         f"({_one_line(error)})") from error


def load_area(spec: str, parameters: Mapping[str, Any] | None = None) -> RestrictedArea:
    """Build the restricted area `spec` names, calling it with `parameters` as keywords.

    `spec` is "package.module:Class" (a dotted attribute path after the colon works too) or the
    name of an entry point in `ENTRY_POINT_GROUP`. The call must return a `RestrictedArea`.
    Raises ValueError, naming the spec, for a missing module or attribute, parameters the
    class refuses (TypeError) or any other failure to build it, and a result of another type.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"restricted area spec must be a non-empty string, got {spec!r}")
    spec = spec.strip()
    parameters = {} if parameters is None else parameters
    if not isinstance(parameters, Mapping) or not all(isinstance(k, str) for k in parameters):
        raise ValueError(f"restricted area {spec!r}: parameters must be a mapping of names to "
                         f"values, got {parameters!r}")
    factory = _resolve(spec)
    if not callable(factory):
        raise ValueError(f"restricted area {spec!r}: {type(factory).__name__} is not callable")
    try:
        area = factory(**parameters)
    except TypeError as error:
        raise ValueError(f"restricted area {spec!r}: bad parameters {sorted(parameters)} "
                         f"({_one_line(error)})") from error
    except Exception as error:  # a user's class may fail any way: one line naming the spec
        raise ValueError(f"restricted area {spec!r}: cannot be built "
                         f"({_one_line(error)})") from error
    if not isinstance(area, RestrictedArea):
        raise ValueError(f"restricted area {spec!r}: built a {type(area).__name__}, not a "
                         f"RestrictedArea (subclass constrained_diffusion_ros.zones."
                         f"RestrictedArea and implement signed_distance)")
    return area
