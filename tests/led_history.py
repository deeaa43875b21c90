"""The LEDs a board emulator lit, read from its switch history, for the tests.

LedBoard re-sends a switch whose reply came late (every command is idempotent): the
emulator then records the same mask twice in a row. Under load that can happen in any run,
so the sequence of masks lit counts a repeated switch once (``masks_lit_since``). A test
that has the LedBoard checks that each repeat it collapsed is explained by a resend
(``repeats_since(...) <= board.resends`` over the same span): a switch sent twice without a
resend is a real double switch, not a late reply.
"""

from __future__ import annotations

from collections.abc import Iterable


def masks_lit_since(history: Iterable[tuple[float, int]], start: float) -> list[int]:
    """The masks switched on at or after ``start`` (``time.monotonic()``), in order, a
    switch repeated back to back counted once."""
    masks = [mask for t, mask in history if t >= start]
    return [m for i, m in enumerate(masks) if i == 0 or m != masks[i - 1]]


def repeats_since(history: Iterable[tuple[float, int]], start: float) -> int:
    """How many switches at or after ``start`` repeated the mask just before them (those
    ``masks_lit_since`` counts once)."""
    masks = [mask for t, mask in history if t >= start]
    return sum(1 for i in range(1, len(masks)) if masks[i] == masks[i - 1])
