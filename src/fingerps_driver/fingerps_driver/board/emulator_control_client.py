"""Client of a board emulator's control channel (``emulator_control.EmulatorControlServer``,
``board_emulator --control PATH``): what the driver's cameras read the lit LEDs through
when the board is an emulator in another process, and what tests inject faults with."""

from __future__ import annotations

import contextlib
import json
import socket
import threading
from typing import Any, Self

from fingerps_driver.board.board_emulator import Fault
from fingerps_driver.board.board_protocol import mask_to_indices
from fingerps_driver.errors import BoardEmulatorError


class BoardEmulatorControl:
    """Client of an ``EmulatorControlServer`` (``board_emulator --control PATH``).

    Connects on first use and again after a failure (the emulator may have been
    restarted). Safe to use from several threads. Every failure to reach the emulator or
    a refused command raises ``BoardEmulatorError``.

    Parameters
    ----------
    path : str
        The control socket.
    timeout_s : float
        How long one command may take.
    """

    def __init__(self, path: str, *, timeout_s: float = 2.0) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        self._path = path
        self._timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._reader: Any = None
        self._lock = threading.Lock()

    @property
    def path(self) -> str:
        return self._path

    def close(self) -> None:
        """Close the connection. Safe to call twice."""
        with self._lock:
            self._close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def command(self, line: str) -> Any:
        """Send one command line; return its result."""
        with self._lock:
            for attempt in range(2):
                try:
                    if self._sock is None:
                        self._connect()
                    assert self._sock is not None
                    self._sock.sendall(line.strip().encode("ascii") + b"\n")
                    raw = self._reader.readline(1 << 22)
                    if not raw.endswith(b"\n"):
                        raise ConnectionError("the emulator closed the control connection")
                    break
                except (OSError, ValueError) as exc:
                    self._close()
                    if attempt:
                        raise BoardEmulatorError(
                            f"cannot reach the board emulator's control socket {self._path} "
                            f"({exc}); start `board_emulator --control {self._path}`") from exc
        answer = json.loads(raw)
        if not answer.get("ok"):
            raise BoardEmulatorError(f"board emulator refused {line.strip()!r}: "
                                     f"{answer.get('error')}")
        return answer.get("result")

    def ping(self) -> bool:
        return bool(self.command("ping"))

    def lit_mask(self) -> int:
        """Mask of the LEDs physically lit now."""
        return int(self.command("lit"))

    def lit_leds(self) -> tuple[int, ...]:
        """Indices of the LEDs physically lit now, ascending."""
        return mask_to_indices(self.lit_mask())

    def state(self) -> dict[str, Any]:
        return dict(self.command("state"))

    def history(self, last: int | None = None) -> list[tuple[float, int]]:
        """(time.monotonic(), mask) of the last switches; monotonic time is system-wide."""
        result = self.command("history" if last is None else f"history {int(last)}")
        return [(float(t), int(mask)) for t, mask in result]

    def inject(self, fault: Fault | str, count: int = 1, *, after: int = 0) -> list[str]:
        """As ``BoardEmulator.inject``; returns the pending faults."""
        name = fault.value if isinstance(fault, Fault) else str(fault).lower()
        return list(self.command(f"inject {name} {int(count)} after {int(after)}"))

    def clear_faults(self) -> None:
        self.command("clear")

    def disconnect(self) -> None:
        self.command("disconnect")

    def reconnect(self) -> None:
        self.command("reconnect")

    def _connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(self._timeout_s)
        try:
            sock.connect(self._path)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self._reader = sock.makefile("rb")

    def _close(self) -> None:
        if self._reader is not None:
            with contextlib.suppress(OSError):
                self._reader.close()
            self._reader = None
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None
