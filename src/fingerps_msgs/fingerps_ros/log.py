"""What the plain classes behind the nodes need of a logger; the node's (rclpy's) provides it.

The plain classes (the driver's board connection, camera set-up and core, the calibration
keeper, the reconstruction worker) take the node's logger so that their lines come out
exactly as the node's would, throttling included; their tests pass a mock or a
``logging.Logger``.
"""

from __future__ import annotations

from typing import Any, Protocol


class Log(Protocol):
    """rclpy's ``RcutilsLogger`` as the nodes use it (``throttle_duration_sec=`` and such)."""

    def info(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at INFO."""
        ...

    def warning(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at WARN."""
        ...

    def error(self, message: str, **kwargs: Any) -> Any:
        """Log ``message`` at ERROR."""
        ...
