"""Declaring ROS parameters with descriptors and refusing bad values with a reason.

Every fingerps node declares each parameter with a description and, for numbers, a range
(shown by ``ros2 param describe``); ``ParameterChecks`` holds per-parameter checks that run
in the on-set callback, so a bad value set at run time is refused with a reason instead of
being taken.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter


class UnknownParameterError(Exception):
    """A parameter file or --ros-args set a parameter the node does not have."""


Check = Callable[[Any], str | None]
"""Returns None when the value is acceptable, else the reason it is refused."""


def descriptor(
    description: str,
    *,
    min_value: float | None = None,
    max_value: float | None = None,
    integer: bool = False,
    read_only: bool = False,
    constraints: str = "",
) -> ParameterDescriptor:
    """Return a ParameterDescriptor with a description and, if given, a numeric range."""
    desc = ParameterDescriptor(
        description=description, read_only=read_only, additional_constraints=constraints)
    if min_value is not None or max_value is not None:
        lo = min_value if min_value is not None else (-(2**62) if integer else -1e300)
        hi = max_value if max_value is not None else (2**62 if integer else 1e300)
        if integer:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return desc


def one_of(*choices: str) -> Check:
    """A check accepting only the given strings."""
    def check(value: Any) -> str | None:
        return None if value in choices else f"must be one of {', '.join(choices)}"
    return check


class ParameterChecks:
    """Checks run on every parameter change of a node; a failing check refuses the change."""

    def __init__(self, node: Node) -> None:
        self._checks: dict[str, Check] = {}
        node.add_on_set_parameters_callback(self._on_set)

    def add(self, name: str, check: Check) -> None:
        """Run ``check`` on every new value of parameter ``name``."""
        self._checks[name] = check

    def refuse_unknown_overrides(self, node: Node) -> None:
        """Raise ``UnknownParameterError`` if the command line or a parameter file set a
        parameter this node never declared (a typo would otherwise be silently ignored)."""
        overrides = getattr(node, "_parameter_overrides", {})
        unknown = sorted(name for name in overrides if not node.has_parameter(name))
        if unknown:
            known = ", ".join(sorted(node.list_parameters([], 0).names))
            raise UnknownParameterError(
                f"{node.get_fully_qualified_name()} has no parameter "
                f"{', '.join(repr(u) for u in unknown)}; its parameters are: {known}")

    def problems(self, parameters: Iterable[Parameter]) -> list[str]:
        """Return 'name: reason' for each parameter whose value a check refuses."""
        found = []
        for param in parameters:
            check = self._checks.get(param.name)
            reason = check(param.value) if check is not None else None
            if reason:
                found.append(f"{param.name}={param.value!r}: {reason}")
        return found

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        found = self.problems(parameters)
        return SetParametersResult(successful=not found, reason="; ".join(found))
