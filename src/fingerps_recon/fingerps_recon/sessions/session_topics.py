"""The topics a recording session can hold: type, QoS, which are recorded by default.

The recorder and the bag replay know a session topic without asking the graph: its ROS 2
type and the QoS it is published with (`fingerps_ros.qos`). Names are relative to the
nodes' namespace; `choose_topics` resolves the ``topics`` parameter's names with the
recorder node's own resolver, so relative and absolute names both work.

No rclpy Node here (QoS profiles are plain values).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from rclpy.qos import QoSProfile

from fingerps_recon.errors import RecorderError
from fingerps_ros import qos, topics


@dataclass(frozen=True)
class RecordedTopic:
    """What the recorder needs to know of a topic without asking the graph."""

    type_name: str
    """ROS 2 type name, ``pkg/msg/Type``."""
    qos: QoSProfile
    """The profile the topic is published with (and subscribed with here)."""

    def subscription_qos(self, depth: int) -> QoSProfile:
        """The topic's profile with a keep-last depth of at least ``depth``."""
        profile = self.qos
        return QoSProfile(history=profile.history, depth=max(profile.depth, depth),
                          reliability=profile.reliability, durability=profile.durability,
                          deadline=profile.deadline, lifespan=profile.lifespan,
                          liveliness=profile.liveliness,
                          liveliness_lease_duration=profile.liveliness_lease_duration)


TOPIC_TABLE: dict[str, RecordedTopic] = {
    topics.FRAMES: RecordedTopic("fingerps_msgs/msg/TaggedFrame", qos.SENSOR_QOS),
    topics.IMAGE_RAW: RecordedTopic("sensor_msgs/msg/Image", qos.SENSOR_QOS),
    topics.CAMERA_INFO: RecordedTopic("sensor_msgs/msg/CameraInfo", qos.SENSOR_QOS),
    topics.BURST: RecordedTopic("fingerps_msgs/msg/Burst", qos.BURST_QOS),
    topics.LIGHT_CALIBRATION: RecordedTopic("fingerps_msgs/msg/LightCalibration",
                                            qos.CALIBRATION_QOS),
    topics.FLAT_FIELD: RecordedTopic("fingerps_msgs/msg/FlatField", qos.CALIBRATION_QOS),
    topics.NORMALS: RecordedTopic("sensor_msgs/msg/Image", qos.OUTPUT_QOS),
    topics.DEPTH: RecordedTopic("sensor_msgs/msg/Image", qos.OUTPUT_QOS),
    topics.ALBEDO: RecordedTopic("sensor_msgs/msg/Image", qos.OUTPUT_QOS),
    topics.POINTS: RecordedTopic("sensor_msgs/msg/PointCloud2", qos.OUTPUT_QOS),
    topics.NORMAL_MAP: RecordedTopic("sensor_msgs/msg/Image", qos.OUTPUT_QOS),
    topics.FINGERPRINT: RecordedTopic("sensor_msgs/msg/Image", qos.OUTPUT_QOS),
}
"""Every topic the recorder can record (names relative to the node's namespace)."""

SESSION_TOPICS: tuple[str, ...] = (
    topics.FRAMES, topics.CAMERA_INFO, topics.BURST, topics.LIGHT_CALIBRATION,
    topics.FLAT_FIELD, topics.NORMALS, topics.DEPTH, topics.ALBEDO, topics.POINTS,
    topics.NORMAL_MAP, topics.FINGERPRINT,
)
"""Recorded by default."""

OUTPUT_TOPICS: frozenset[str] = frozenset(
    {topics.NORMALS, topics.DEPTH, topics.ALBEDO, topics.POINTS, topics.NORMAL_MAP,
     topics.FINGERPRINT})
"""The heavy reconstruction outputs that ``record_outputs:=false`` leaves out."""

Resolve = Callable[[str], str]
"""A node's topic name resolver (``Node.resolve_topic_name``): name -> fully qualified."""


def known_topic(name: str, resolve: Resolve) -> str | None:
    """The table key a (relative or absolute) topic name resolves to, or None."""
    try:
        resolved = resolve(name)
    except Exception:  # rclpy raises several kinds for bad names
        return None
    for key in TOPIC_TABLE:
        if resolve(key) == resolved:
            return key
    return None


def topics_problem(names: Iterable[str], resolve: Resolve) -> str | None:
    """Why a ``topics`` parameter value is refused (names not in the table), or None."""
    unknown = [t for t in names if known_topic(t, resolve) is None]
    if unknown:
        return (f"unknown topics {unknown}; the recorder knows {', '.join(TOPIC_TABLE)} "
                "(relative to its namespace)")
    return None


def choose_topics(requested: Iterable[str], *, record_outputs: bool,
                  resolve: Resolve) -> dict[str, RecordedTopic]:
    """Fully qualified name -> table entry of every topic to record.

    Raises
    ------
    RecorderError
        A name not in the table, or nothing left to record.
    """
    chosen: dict[str, RecordedTopic] = {}
    for name in requested:
        key = known_topic(name, resolve)
        if key is None:  # only reachable if the on-set check was bypassed
            raise RecorderError(f"unknown topic {name!r}; known: {', '.join(TOPIC_TABLE)}")
        if key in OUTPUT_TOPICS and not record_outputs:
            continue
        chosen[resolve(key)] = TOPIC_TABLE[key]
    if not chosen:
        raise RecorderError(
            "nothing to record: 'topics' is empty (or holds only outputs and "
            "record_outputs is false); give at least one topic")
    return chosen

