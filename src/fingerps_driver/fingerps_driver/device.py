"""What a burst needs of every device it drives: opened once, closed again, usable in ``with``.

The cameras (``cameras.camera.Camera``) and the LED board's serial client
(``board.led_board.LedBoard``) share this lifecycle: ``open`` acquires the device and does
nothing if it is open already, ``close`` releases it and is safe to call twice, and a
``with`` block opens the device and closes it again, also after an error. A device
implements only what differs: ``is_open``, ``_acquire`` and ``_release``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Self


class Device(ABC):
    """A device that is opened before use and closed after it."""

    @property
    @abstractmethod
    def is_open(self) -> bool:
        """True between a successful ``open`` and ``close``."""

    def open(self) -> None:
        """Acquire the device; nothing if it is open already.

        Raises the device's error (a ``FingerpsDriverError``) saying what to check when it
        cannot be opened; the device is then not open.
        """
        if not self.is_open:
            self._acquire()

    def close(self) -> None:
        """Release the device. Safe to call twice."""
        self._release()

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @abstractmethod
    def _acquire(self) -> None:
        """Open the device (called by ``open`` only when it is not open)."""

    @abstractmethod
    def _release(self) -> None:
        """Close the device if it is open; never raises for a device already gone."""
