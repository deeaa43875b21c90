"""The LEDs a board emulator lit, read from its switch history, for the tests.

LedBoard re-sends a switch whose reply came late (every command is idempotent): the
emulator then records the same mask twice in a row. Under load that can happen in any run,
so the sequence of masks lit counts a repeated switch once.
"""

from __future__ import annotations

from collections.abc import Iterable


def masks_lit_since(history: Iterable[tuple[float, int]], start: float) -> list[int]:
    """The masks switched on at or after ``start`` (``time.monotonic()``), in order, a
    switch repeated back to back counted once."""
    masks = [mask for t, mask in history if t >= start]
    return [m for i, m in enumerate(masks) if i == 0 or m != masks[i - 1]]
