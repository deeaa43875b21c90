"""Declaring ROS parameters with descriptors and refusing bad values with a reason.

Every fingerps node declares its parameter table (`fingerps_ros.parameter_table`: each
parameter with a description and, for numbers, a range, shown by ``ros2 param describe``)
with `declare_parameters`; ``ParameterChecks`` holds the per-parameter checks that run in
the on-set callback, so a bad value set at run time is refused with a reason instead of
being taken.
"""

from __future__ import annotations

from collections.abc import Iterable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from fingerps_ros.parameter_table import Check, ParameterRow


class UnknownParameterError(Exception):
    """A parameter file or --ros-args set a parameter the node does not have."""


def row_descriptor(row: ParameterRow) -> ParameterDescriptor:
    """The ParameterDescriptor of a row of a parameter table (what ``ros2 param describe``
    shows of it): description, read-only, constraints, dynamic typing and, if the row has
    bounds, its numeric range (an open side unbounded)."""
    desc = ParameterDescriptor(
        description=row.description, read_only=row.read_only,
        additional_constraints=row.constraints, dynamic_typing=row.dynamic_typing)
    if row.min_value is not None or row.max_value is not None:
        integer = row.integer
        lo = row.min_value if row.min_value is not None else (-(2**62) if integer else -1e300)
        hi = row.max_value if row.max_value is not None else (2**62 if integer else 1e300)
        if integer:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            desc.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return desc


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


def declare_parameters(node: Node, rows: Iterable[ParameterRow], *,
                       check_while_declaring: bool = True,
                       checks: ParameterChecks | None = None) -> ParameterChecks:
    """Declare ``rows`` on ``node`` in their order, each with its descriptor; return the
    checks (for more parameters, and ``refuse_unknown_overrides``).

    A row's callable default is evaluated just before the row is declared (so it may read
    the parameters declared before it). Each row's check is in force from its declaration
    on: a bad value given at start raises rclpy's ``InvalidParameterValueException``, which
    ``run_node`` reports in one line. With ``check_while_declaring=False`` the checks are
    added after the last row, for a node that names every bad start value at once
    (``ParameterChecks.problems``). ``checks``: the node's checks to add to (a part of a node
    declaring its own rows, e.g. ``compressed_topics``), else new ones.
    """
    checks = ParameterChecks(node) if checks is None else checks
    table = tuple(rows)
    for row in table:
        if check_while_declaring and row.check is not None:
            checks.add(row.name, row.check)
        node.declare_parameter(row.name, row.default_value(), row_descriptor(row))
    if not check_while_declaring:
        for row in table:
            if row.check is not None:
                checks.add(row.name, row.check)
    return checks
