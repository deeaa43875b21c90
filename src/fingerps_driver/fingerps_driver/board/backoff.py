"""Exponential back-off between attempts to reconnect to the LED board."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Backoff:
    """Delays ``initial_s``, ``initial_s * factor``, ... capped at ``max_s``.

    Attributes
    ----------
    initial_s : float
        Delay before the first attempt, seconds (> 0).
    max_s : float
        Longest delay, seconds (>= initial_s).
    factor : float
        Growth per failed attempt (>= 1).
    """

    initial_s: float = 0.5
    max_s: float = 10.0
    factor: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.initial_s) and self.initial_s > 0):
            raise ValueError(f"initial_s {self.initial_s} must be > 0")
        if not (math.isfinite(self.max_s) and self.max_s >= self.initial_s):
            raise ValueError(f"max_s {self.max_s} must be >= initial_s {self.initial_s}")
        if not (math.isfinite(self.factor) and self.factor >= 1):
            raise ValueError(f"factor {self.factor} must be >= 1")

    def delay_s(self, attempt: int) -> float:
        """Delay before attempt ``attempt`` (0 = the first after the loss)."""
        if attempt < 0:
            raise ValueError(f"attempt {attempt} must be >= 0")
        # log-domain comparison: no overflow for a board that stays away for days
        if attempt * math.log(self.factor) >= math.log(self.max_s / self.initial_s):
            return self.max_s
        return self.initial_s * self.factor**attempt
