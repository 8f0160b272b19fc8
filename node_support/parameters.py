"""Every node's parameters in one table each: declared with descriptors (description, range,
read-only), checked at start and at run time with a reason, and printed by `--help`.

A double parameter also takes an integer (`-p zone_lifetime:=2`), as users type them, and holds
it as a double (2.0: what `ros2 param get` shows and parameter events carry); NaN and values out
of range are refused with the parameter's name and range.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from msg_schemas.contract import NAMESPACE, SERVICES, TOPICS

if TYPE_CHECKING:  # rclpy is imported where a node is built: `--help` comes without it
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node

Value = bool | int | float | str | list


@dataclass(frozen=True)
class Param:
    name: str
    default: Value
    description: str
    read_only: bool = False  # read at start only
    low: float | None = None  # inclusive
    high: float | None = None
    choices: tuple[str, ...] = ()

    def reason(self, value: object) -> str | None:
        """Why `value` is refused, or None."""
        kind = type(self.default)
        if kind is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or not math.isfinite(value):
                return f"parameter {self.name} needs a finite number, got {value!r}"
        elif kind is list:
            if not isinstance(value, list | tuple) or len(value) != len(self.default):
                return f"parameter {self.name} needs {len(self.default)} numbers, got {value!r}"
        elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            return f"parameter {self.name} needs a {kind.__name__}, got {value!r}"
        if self.choices and value not in self.choices:
            return f"parameter {self.name} must be one of {list(self.choices)}, got {value!r}"
        if (self.low is not None and value < self.low) or \
                (self.high is not None and value > self.high):
            return f"parameter {self.name} must be in [{self.range_text()}], got {value!r}"
        return None

    def range_text(self) -> str:
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        return f"{low}, {high}"

    def descriptor(self) -> ParameterDescriptor:
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

        descriptor = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if isinstance(self.default, float):
            descriptor.dynamic_typing = True  # an integer is taken too; `reason` checks it
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=-math.inf if self.low is None else float(self.low),
                to_value=math.inf if self.high is None else float(self.high))]
        elif isinstance(self.default, int) and not isinstance(self.default, bool) and \
                self.low is not None and self.high is not None:
            descriptor.integer_range = [IntegerRange(from_value=int(self.low),
                                                     to_value=int(self.high))]
        if self.choices:
            descriptor.additional_constraints = f"one of {', '.join(self.choices)}"
        return descriptor


def declare(node: Node, params: Sequence[Param]) -> dict[str, Value]:
    """Declares `params` on `node` and returns their start values, checked (ValueError with the
    reason otherwise); later changes are checked the same way before they are taken."""
    from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
    from rclpy.parameter import Parameter

    by_name = {param.name: param for param in params}
    doubles = {param.name for param in params if isinstance(param.default, float)}
    values = {}
    for param in params:
        descriptor = param.descriptor()
        if param.name not in doubles:
            value = node.declare_parameter(param.name, param.default, descriptor).value
        else:  # declared writable, so that an integer given can be set again as a double
            writable = ParameterDescriptor()
            writable.dynamic_typing = True
            value = node.declare_parameter(param.name, param.default, writable).value
        reason = param.reason(value)
        if reason:
            raise ValueError(reason)
        if param.name in doubles:
            if not isinstance(value, float):
                value = float(value)
                node.set_parameters([Parameter(param.name, Parameter.Type.DOUBLE, value)])
            node.set_descriptor(param.name, descriptor)  # read-only, range: from here on
        values[param.name] = value

    def as_doubles(changes: list[Parameter]) -> list[Parameter]:
        """An integer set at run time (`ros2 param set ... zone_lifetime 3`) becomes a double,
        as one given at start does."""
        return [Parameter(change.name, Parameter.Type.DOUBLE, float(change.value))
                if change.name in doubles and change.type_ == Parameter.Type.INTEGER
                else change for change in changes]

    def on_set(changes) -> SetParametersResult:
        for change in changes:
            param = by_name.get(change.name)
            if param is not None and change.type_ != ParameterType.PARAMETER_NOT_SET:
                reason = param.reason(change.value)
                if reason:
                    return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    node.add_pre_set_parameters_callback(as_doubles)
    node.add_on_set_parameters_callback(on_set)
    return values


def usage(node_name: str, summary: str, params: Sequence[Param]) -> str:
    """`--help`: what the node does, its parameters and its topics and services (from the
    contract), and how to set them."""
    lines = [f"usage: {node_name} [--ros-args [-p NAME:=VALUE]... [-r FROM:=TO]... "
             f"[--params-file FILE]]", "", summary.strip(), "", "parameters:"]
    for param in params:
        bounds = f", range [{param.range_text()}]" if param.low is not None or \
            param.high is not None else ""
        choices = f", one of {list(param.choices)}" if param.choices else ""
        start = ", read at start" if param.read_only else ""
        lines.append(f"  {param.name} (default {param.default!r}{bounds}{choices}{start})")
        lines.append(f"      {param.description}")
    lines += ["", f"topics and services (relative: in namespace /{NAMESPACE} unless -r "
              f"__ns:=/other):"]
    for endpoint in TOPICS.values():
        role = "publishes" if endpoint.publisher == node_name else \
            "subscribes" if node_name in endpoint.subscribers else None
        if role:
            lines.append(f"  {role} {endpoint.name} ({endpoint.type}): {endpoint.description}")
    for endpoint in SERVICES.values():
        if endpoint.publisher == node_name:
            lines.append(f"  serves {endpoint.name} ({endpoint.type}): {endpoint.description}")
    return "\n".join(lines)


def answered_help(args: list[str] | None, name: str, summary: str,
                  parameters: Sequence[Param]) -> bool:
    """Prints the node's usage if `-h` or `--help` comes before `--ros-args`. Here, with the
    table, so that a node's `main` answers before it imports rclpy, torch or the model."""
    argv = sys.argv[1:] if args is None else list(args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "-h" in own or "--help" in own:
        print(usage(name, summary, parameters))
        return True
    return False
