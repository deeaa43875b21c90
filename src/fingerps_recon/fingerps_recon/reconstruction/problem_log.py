"""Problems told in one log line each: an exception's one-line form (:func:`one_line`) and
the gate that lets the same problem through at most once a period (:class:`LogGate`)."""

from __future__ import annotations

import threading
import time
import traceback
from pathlib import Path


def one_line(exc: BaseException) -> str:
    """``Type: message (at file.py:line)`` of an exception: one log line, no traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" (at {Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    message = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {message}{where}"


class LogGate:
    """Whether to log a problem: every new one, the same one again at most every
    ``period_s`` (a stream of identical bad bursts gives one line per period, a mix of
    different problems one line each)."""

    def __init__(self, period_s: float = 5.0, keep: int = 64) -> None:
        self._period_s = period_s
        self._keep = keep
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def opens(self, problem: str) -> bool:
        """True if ``problem`` is to be logged now (and remembered as logged now)."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(problem)
            if last is not None and now - last < self._period_s:
                return False
            if len(self._last) >= self._keep:
                self._last = {p: t for p, t in self._last.items()
                              if now - t < self._period_s}
            self._last[problem] = now
            return True
