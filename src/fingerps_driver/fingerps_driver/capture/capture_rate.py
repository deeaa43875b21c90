"""Whether continuous capture keeps the rate asked for (the driver's ``rate`` parameter).

A timer asks for a burst every 1/rate seconds; when a burst takes longer than that (a slow
camera, a loaded machine), the timer's calls queue behind it and fewer bursts come out than
asked for. :class:`CaptureRate` counts the bursts captured over a sliding window so that the
driver's diagnostics can say so.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class RateReport:
    """What :meth:`CaptureRate.report` found."""

    requested: float          # bursts per second asked for (0: on request only)
    achieved: float | None    # bursts per second over the window; None before a full window
    behind: bool              # achieved below ``tolerance`` x requested


class CaptureRate:
    """Bursts captured in continuous mode over the last ``window_s`` seconds.

    Times are the caller's monotonic clock, seconds. A change of rate restarts the window.
    """

    def __init__(self, *, window_s: float = 5.0, tolerance: float = 0.9) -> None:
        if not window_s > 0 or not 0 < tolerance <= 1:
            raise ValueError(f"window_s must be > 0 and tolerance in (0, 1], got {window_s}, "
                             f"{tolerance}")
        self._window_s = window_s
        self._tolerance = tolerance
        self._rate = 0.0
        self._since = 0.0
        self._times: deque[float] = deque()

    def set_rate(self, rate: float, now: float) -> None:
        """The rate asked for from ``now`` on (0: continuous capture off)."""
        self._rate = max(0.0, float(rate))
        self._since = now
        self._times.clear()

    def captured(self, now: float) -> None:
        """A continuous burst was captured at ``now``."""
        self._times.append(now)
        self._forget(now)

    def report(self, now: float) -> RateReport:
        """The rate asked for, the rate achieved over the last full window, and whether
        capture falls behind."""
        self._forget(now)
        if self._rate <= 0 or now - self._since < self._window_s:
            return RateReport(self._rate, None, False)
        achieved = len(self._times) / self._window_s
        return RateReport(self._rate, achieved, achieved < self._tolerance * self._rate)

    def _forget(self, now: float) -> None:
        while self._times and self._times[0] <= now - self._window_s:
            self._times.popleft()
