"""The key the graph tests file a received message under: its header's stamp.

The outputs of one burst carry the burst's stamp, so messages of different topics keyed by
``stamp_key(msg.header)`` are matched up by it.
"""

from __future__ import annotations

from std_msgs.msg import Header


def stamp_key(header: Header) -> tuple[int, int]:
    """``(sec, nanosec)`` of ``header.stamp``."""
    return header.stamp.sec, header.stamp.nanosec
