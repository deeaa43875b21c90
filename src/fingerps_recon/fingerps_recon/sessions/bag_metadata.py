"""A rosbag2 bag's information, as ``metadata.yaml`` and the MCAP ``rosbag2`` record hold it
(rosbag2_storage's BagMetadata, version 9): the pieces of a bag (`BagPiece`), what a
finished bag holds (`BagSummary`) and the YAML nodes of its metadata (`bag_metadata`)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

METADATA_FILENAME = "metadata.yaml"
METADATA_VERSION = 9
STORAGE_IDENTIFIER = "mcap"
INT64_MAX = 2**63 - 1
"""rosbag2's starting_time of a bag without messages; also RMW_DURATION_INFINITE in ns."""


@dataclass(frozen=True)
class BagPiece:
    """One MCAP file of a bag, as metadata.yaml's ``files`` lists it.

    Attributes
    ----------
    path : Path
        The MCAP file.
    starting_time_ns : int
        Earliest log time in it (`INT64_MAX` without messages).
    duration_ns : int
        Latest minus earliest log time.
    message_count : int
        Messages in it.
    size_bytes : int
        Bytes of the finished file.
    """

    path: Path
    starting_time_ns: int = INT64_MAX
    duration_ns: int = 0
    message_count: int = 0
    size_bytes: int = 0


@dataclass(frozen=True)
class BagSummary:
    """What a finished bag holds.

    Attributes
    ----------
    path : Path
        The bag directory.
    mcap_path : Path
        Its first MCAP file (``DIR_0.mcap``).
    pieces : tuple[BagPiece, ...]
        Every MCAP file of the bag, in order (one unless the bag was split).
    message_counts : dict[str, int]
        Messages per topic, in the order the topics were added.
    message_count : int
        All messages.
    starting_time_ns : int
        Earliest log time (`INT64_MAX` when there is no message, as rosbag2 writes).
    duration_ns : int
        Latest minus earliest log time.
    """

    path: Path
    mcap_path: Path
    pieces: tuple[BagPiece, ...] = ()
    message_counts: dict[str, int] = field(default_factory=dict)
    message_count: int = 0
    starting_time_ns: int = INT64_MAX
    duration_ns: int = 0


def bag_metadata(summary: BagSummary, pieces: Sequence[BagPiece], topics: Iterable[Any], *,
             custom_data: Mapping[str, str], ros_distro: str) -> dict[str, Any]:
    """rosbag2's BagMetadata as YAML nodes (yaml.hpp convert<BagMetadata>::encode order):
    ``topics`` the bag's topics in the order they were added (each with ``name``,
    ``type_name``, ``serialization_format``, ``offered_qos``, ``type_hash``,
    ``message_count``)."""
    topic_nodes = [
        {
            "topic_metadata": {
                "name": topic.name,
                "type": topic.type_name,
                "serialization_format": topic.serialization_format,
                "offered_qos_profiles": topic.offered_qos,
                "type_description_hash": topic.type_hash,
            },
            "message_count": topic.message_count,
        }
        for topic in topics
    ]
    return {
        "version": METADATA_VERSION,
        "storage_identifier": STORAGE_IDENTIFIER,
        "duration": {"nanoseconds": summary.duration_ns},
        "starting_time": {"nanoseconds_since_epoch": summary.starting_time_ns},
        "message_count": summary.message_count,
        "topics_with_message_count": topic_nodes,
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [piece.path.name for piece in pieces],
        "files": [{
            "path": piece.path.name,
            "starting_time": {"nanoseconds_since_epoch": piece.starting_time_ns},
            "duration": {"nanoseconds": piece.duration_ns},
            "message_count": piece.message_count,
        } for piece in pieces],
        "custom_data": dict(custom_data) or None,
        "ros_distro": ros_distro,
    }
