"""The one framing loop of the LED board's two ends: the serial client and the emulator.

Both wait for bytes on a file descriptor (``select``), read what has arrived and cut it into
protocol lines with ``board_protocol.LineFramer``, which resynchronises on garbage: bytes
before a sigil are dropped, a sigil mid-line restarts the line, an overlong line is dropped.
The client (``led_board.LedBoard``) reads replies until its timeout's deadline; the
emulator (``board_emulator.BoardEmulator``) reads requests until its stop event is set.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Callable, Iterator

from fingerps_driver.board.board_protocol import LineFramer

POLL_S = 0.05
"""Longest wait without a deadline before the stop event is looked at again."""
READ_BYTES = 4096
"""At most this many bytes are read at a time."""


class FrameReader:
    """Complete protocol lines starting with ``sigil``, as they arrive on ``fileno``.

    Parameters
    ----------
    fileno : int
        The descriptor to wait on (the serial port, the pty's master side).
    read : callable
        ``read(n)`` returns the bytes that have arrived, at most ``n``; its errors (a port
        that vanished) propagate out of ``lines``.
    sigil : bytes
        ``board_protocol.REPLY_SIGIL`` for the client, ``REQUEST_SIGIL`` for the board.
    wake_fd : int or None
        A descriptor that, once readable, makes ``lines`` look at its stop event at once.
    """

    def __init__(
        self,
        fileno: int,
        read: Callable[[int], bytes],
        sigil: bytes,
        *,
        wake_fd: int | None = None,
    ) -> None:
        self._fileno = fileno
        self._read = read
        self._framer = LineFramer(sigil)
        self._wait_on = [fileno] if wake_fd is None else [fileno, wake_fd]

    def reset(self) -> None:
        """Forget any partial line (before a new request, with the input discarded)."""
        self._framer.reset()

    def lines(
        self, *, deadline: float | None = None, stop: threading.Event | None = None
    ) -> Iterator[bytes]:
        """Yield each complete line (sigil included, newline excluded) as it arrives.

        Ends once ``deadline`` (``time.monotonic()``) has passed, or when ``stop`` is set
        (looked at every ``POLL_S`` at the latest, and at once when ``wake_fd`` becomes
        readable); without either it runs until the caller stops iterating. A partial line
        is kept for the next call.
        """
        while stop is None or not stop.is_set():
            wait = POLL_S if deadline is None else deadline - time.monotonic()
            if wait <= 0:
                return
            ready, _, _ = select.select(self._wait_on, [], [], wait)
            if ready != [self._fileno]:  # nothing arrived, or woken to look at stop
                continue
            yield from self._framer.feed(self._read(READ_BYTES))
