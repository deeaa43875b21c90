"""A node's parameter table: one `ParameterRow` per parameter, in declaration order.

A row is what ``ros2 param describe`` shows of a parameter (description, range, integer or
not, read-only, further constraints in words), its default, and the check that refuses a bad
value with a reason. ``fingerps_ros.parameters.declare_parameters`` declares a table on a
node. No ROS here (plain data and plain checks), so a science room (``scan``) may hold its
node's table.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

Check = Callable[[Any], str | None]
"""Returns None when the value is acceptable, else the reason it is refused."""


@dataclass(frozen=True)
class ParameterRow:
    """One parameter of a node's table.

    ``default`` may be a callable without arguments, evaluated when the row is declared
    (e.g. one that reads a parameter declared before it). ``min_value``/``max_value`` give
    its range (an integer range if ``integer``); ``constraints`` says in words what else it
    must be; ``check`` refuses a bad value with a reason; ``dynamic_typing`` lets the value
    change type (a per-LED array that may be empty).
    """

    name: str
    default: Any
    description: str
    min_value: float | None = None
    max_value: float | None = None
    integer: bool = False
    read_only: bool = False
    constraints: str = ""
    check: Check | None = None
    dynamic_typing: bool = False

    def default_value(self) -> Any:
        """The default, evaluated if it is a callable."""
        return self.default() if callable(self.default) else self.default


def one_of(*choices: str) -> Check:
    """A check accepting only the given strings."""
    def check(value: Any) -> str | None:
        return None if value in choices else f"must be one of {', '.join(choices)}"
    return check


def check_finite(value: object) -> str | None:
    """A check accepting only a finite number."""
    try:
        finite = math.isfinite(float(value))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        finite = False
    return None if finite else "must be a finite number"
