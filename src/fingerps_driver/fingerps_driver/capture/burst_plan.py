"""What one burst captures: the LED order and each LED's exposure and drive level.

The driver node's parameters ``led_order``, ``exposure_time``/``exposure_times`` and
``led_level``/``led_levels`` become a ``BurstPlan`` here; the checks return the reason a
value is refused (or None), so the node can refuse a bad value when it is set. Per-LED
lists are indexed by LED index (entry i is LED i's), whatever the order of capture.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

MAX_EXPOSURE_S = 1.0
MIN_EXPOSURE_S = 1e-5


@dataclass(frozen=True)
class BurstPlan:
    """The LEDs of a burst in capture order, with the exposure and level of each entry.

    Attributes
    ----------
    led_order : tuple of int
        LED indices in capture order (no repeats).
    exposures_s : tuple of float
        Exposure of each entry of ``led_order``, seconds.
    levels : tuple of float
        Relative drive level 0..1 of each entry of ``led_order``.
    """

    led_order: tuple[int, ...]
    exposures_s: tuple[float, ...]
    levels: tuple[float, ...]


def check_led_order(order: Sequence[int], led_count: int) -> str | None:
    """Reason ``order`` is not a valid LED order for ``led_count`` LEDs, or None.

    Valid: at least one LED, each in 0..led_count-1, none twice (a permutation of a
    subset of the LEDs).
    """
    values = list(order)
    if not values:
        return "is empty; give the LEDs to capture, e.g. [0, 1, 2, 3, 4, 5, 6]"
    beyond = sorted({v for v in values if not 0 <= v < led_count})
    if beyond:
        return f"names LED(s) {beyond} beyond the board's 0..{led_count - 1}"
    twice = sorted({v for v in values if values.count(v) > 1})
    if twice:
        return f"names LED(s) {twice} more than once"
    return None


def check_exposures(values: Sequence[float] | None, led_count: int) -> str | None:
    """Reason a per-LED exposure list is refused, or None (None/empty = not used)."""
    return _check_per_led(values, led_count, MIN_EXPOSURE_S, MAX_EXPOSURE_S,
                          f"exposures are seconds in {MIN_EXPOSURE_S:g}..{MAX_EXPOSURE_S:g}")


def check_levels(values: Sequence[float] | None, led_count: int) -> str | None:
    """Reason a per-LED level list is refused, or None (None/empty = not used)."""
    return _check_per_led(values, led_count, 0.0, 1.0, "levels are in 0..1")


def _check_per_led(values: Sequence[float] | None, led_count: int, low: float, high: float,
                   rule: str) -> str | None:
    """Reason a per-LED list is refused: not one entry per LED, or values outside low..high."""
    if not values:
        return None
    if len(values) != led_count:
        return f"has {len(values)} entries for {led_count} LEDs; give one per LED, or none"
    bad = [v for v in values if not (math.isfinite(v) and low <= v <= high)]
    if bad:
        return f"holds {bad}: {rule}"
    return None


def make_plan(
    *,
    led_count: int,
    led_order: Sequence[int],
    exposure_time: float,
    exposure_times: Sequence[float] | None = None,
    led_level: float,
    led_levels: Sequence[float] | None = None,
) -> BurstPlan:
    """The plan of a burst from the driver's parameters.

    ``exposure_times``/``led_levels`` (one per LED, indexed by LED) win over
    ``exposure_time``/``led_level`` (the same for all) when given and not empty.

    Raises
    ------
    ValueError
        A value the checks refuse; the message names the parameter and the reason.
    """
    order = tuple(int(v) for v in led_order)
    for name, reason in (
        ("led_order", check_led_order(order, led_count)),
        ("exposure_times", check_exposures(exposure_times, led_count)),
        ("led_levels", check_levels(led_levels, led_count)),
    ):
        if reason:
            raise ValueError(f"{name} {reason}")
    if not (math.isfinite(exposure_time) and MIN_EXPOSURE_S <= exposure_time <= MAX_EXPOSURE_S):
        raise ValueError(f"exposure_time {exposure_time} outside "
                         f"{MIN_EXPOSURE_S:g}..{MAX_EXPOSURE_S:g} s")
    if not (math.isfinite(led_level) and 0.0 <= led_level <= 1.0):
        raise ValueError(f"led_level {led_level} outside 0..1")
    exposures = list(exposure_times) if exposure_times else [exposure_time] * led_count
    levels = list(led_levels) if led_levels else [led_level] * led_count
    return BurstPlan(
        led_order=order,
        exposures_s=tuple(float(exposures[led]) for led in order),
        levels=tuple(float(levels[led]) for led in order),
    )
