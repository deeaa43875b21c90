"""Waiting for a condition by polling it, for the core and the graph tests.

A test that waits for another thread or process polls instead of sleeping blindly: the
condition is evaluated every ``interval_s`` until it holds or ``timeout_s`` has passed, and
once more at the end, so a slow machine only makes the test slower, never wrong.
"""

from __future__ import annotations

import time
from collections.abc import Callable


def poll_until(predicate: Callable[[], object], timeout_s: float, *,
               interval_s: float = 0.05) -> bool:
    """Whether ``predicate()`` became truthy within ``timeout_s`` seconds, evaluated every
    ``interval_s`` (and once after the deadline). The test keeps its own assertions."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(interval_s)
