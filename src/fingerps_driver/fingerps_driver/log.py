"""What the driver's plain classes need of a logger: the node's (rclpy's) logger provides it.

The plain classes (board connection, camera set-up, driver core) take the node's logger so
that their lines come out exactly as the node's would, throttling included; the tests pass
a recorder.
"""

from __future__ import annotations

from typing import Any, Protocol


class Log(Protocol):
    """rclpy's ``RcutilsLogger`` as the driver uses it (``throttle_duration_sec=`` and such)."""

    def info(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at INFO."""
        ...

    def warning(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at WARN."""
        ...

    def error(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at ERROR."""
        ...
