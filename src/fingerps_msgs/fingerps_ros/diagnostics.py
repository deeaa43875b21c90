"""A node's ``/diagnostics``: its statuses as one stamped ``DiagnosticArray``.

Every fingerps node publishes its statuses once a second from a timer of its own
(``PERIOD_S``, diagnostic_updater's habit without its dependency), and the driver, calib and
scan nodes also at once when something they report changes; the statuses come from the
node's plain core (``driver_diagnostics``, ``calib_diagnostics``,
``reconstruction.diagnostics`` ...).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from fingerps_ros import topics

if TYPE_CHECKING:
    from rclpy.node import Node

PERIOD_S = 1.0  # how often a node publishes its statuses unasked


def key_values(values: Mapping[str, str]) -> list[KeyValue]:
    """``values`` as a status's ``KeyValue`` list, in their order."""
    return [KeyValue(key=key, value=value) for key, value in values.items()]


class DiagnosticsPublisher:
    """Publishes ``statuses()`` on ``/diagnostics``, stamped with ``node``'s clock.

    Parameters
    ----------
    node : rclpy.node.Node
        The node that publishes.
    statuses : callable
        The node's statuses now.
    """

    def __init__(self, node: Node,
                 statuses: Callable[[], Sequence[DiagnosticStatus]]) -> None:
        self._node = node
        self._statuses = statuses
        self._publisher = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)

    def publish(self) -> None:
        """Publish the statuses now."""
        array = DiagnosticArray(status=list(self._statuses()))
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(array)
