"""Something served by a background thread between ``start`` and ``stop`` (the board
emulator on its pty, the emulator's control channel on its socket); ``with`` does both."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Self


class Served(ABC):
    """Served by a background thread between ``start`` and ``stop``; ``with`` does both."""

    @abstractmethod
    def start(self) -> None:
        """Start serving."""

    @abstractmethod
    def stop(self) -> None:
        """Stop serving. Safe to call twice."""

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


