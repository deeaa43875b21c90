"""recorder_node: records a fingerps session into a rosbag2 MCAP bag.

Subscribes to the session topics with ``raw=True`` (the serialized CDR bytes are written as
they arrive, nothing is deserialized) using each topic's QoS from `fingerps_ros.qos`
(calibration topics reliable + transient-local, so the calibration in force when recording
starts is recorded too), and writes them with `fingerps_recon.sessions.session_bag.SessionBagWriter`
into ``<bags_dir>/<session_name>/`` (``metadata.yaml`` + ``<session_name>_0.mcap``, and
``_1.mcap``, ... when split), which ``ros2 bag info/play``, rosbags and Foxglove read.

At kiosk scale: ``max_bagfile_size`` / ``max_bagfile_duration`` split the bag into pieces as
rosbag2's options of the same names do (each piece a complete MCAP file, all listed in
metadata.yaml), and ``bags_dir_limit_mb`` caps the sessions in ``bags_dir``: the oldest whole
sessions are removed first (`sessions.session_retention`), at start, at each new piece
and every ``RETENTION_PERIOD_S`` seconds, never the session being recorded.

Nothing is lost silently. A message the recorder subscribed to and did not write is counted
per topic and reason: ``lost_before_recorder`` (skipped in the publisher's sequence numbers,
`fingerps_recon.sessions.sequence_gaps`: DDS overwrote or missed it before the recorder took it),
``dropped_writer_behind`` (the write queue was full), ``write_errors``, ``unrecordable``
(the bag refused the topic). The counts are on ``/diagnostics`` (status ``recorder:
recording``, WARN while losses keep happening, ERROR while writes fail) and in the finished
bag: metadata.yaml's ``custom_data`` ``fingerps.not_written`` and the MCAP metadata record
``fingerps.recorder.not_written``.

Threads: a subscription callback only stamps the message and appends it to a queue (on a
topic's first message it also registers the topic, with the publishers' QoS as the graph
shows them, as rosbag2 does). A writer thread takes the messages from the queue, writes
them, and closes the open MCAP chunk every ``flush_period`` seconds, so compression never
blocks intake. The queue is bounded in bytes (``queue_limit_mb``) and drops the oldest
message when full; drops are counted, logged (throttled) and reported at the end.

Shutdown: SIGINT and SIGTERM both shut the rclpy context down (rclpy Jazzy installs handlers
for both), the spin ends, and ``destroy_node()`` drains the queue and finishes the bag, so
the MCAP file gets its summary and the directory its metadata.yaml. A killed process
(SIGKILL) loses the open chunk at most; ``ros2 run fingerps_recon bag_recover <bag>``
(`fingerps_recon.sessions.bag_recovery`) turns the rest into a valid bag and says what was lost.

MCAP metadata records: ``fingerps.software`` (package version, ROS distro, RMW, Python,
mcap library) and ``fingerps.recorder.parameters`` (every parameter in force). The
calibration used is in the bag as the calibration topics' messages.
"""

from __future__ import annotations

import functools
import json
import os
import platform
import threading
import time
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import rclpy.logging
from ament_index_python.packages import get_package_share_directory
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.utilities import get_rmw_implementation_identifier

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.sessions.message_definition import load_message_definition, split_type_name
from fingerps_recon.sessions.sequence_gaps import SequenceGaps
from fingerps_recon.sessions.session_bag import (
    DEFAULT_CHUNK_SIZE,
    NS_PER_S,
    QosProfileFields,
    SessionBagError,
    SessionBagWriter,
    qos_profiles_yaml,
)
from fingerps_recon.sessions.session_retention import RetentionResult, enforce_limit
from fingerps_ros import qos, topics
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import ParameterChecks, descriptor

PACKAGE = "fingerps_recon"
RETENTION_PERIOD_S = 10.0
"""How often the writer thread checks ``bags_dir_limit_mb`` between pieces."""
HEALTH_WINDOW_S = 10.0
"""/diagnostics warns while messages went unwritten within this many seconds."""
MiB = 1024 * 1024


@dataclass(frozen=True)
class RecordedTopic:
    """What the recorder needs to know of a topic without asking the graph."""

    type_name: str
    """ROS 2 type name, ``pkg/msg/Type``."""
    qos: QoSProfile
    """The profile the topic is published with (and subscribed with here)."""


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


class RecorderError(FingerpsReconError):
    """The recorder cannot start with the parameters given."""


def default_session_name(now: datetime | None = None) -> str:
    """``fingerps_<UTC date-time>``, e.g. ``fingerps_20250131T120000Z``."""
    now = now or datetime.now(UTC)
    return f"fingerps_{now.astimezone(UTC):%Y%m%dT%H%M%SZ}"


def software_version() -> str:
    """Version of fingerps_recon: its Python distribution, else its package.xml."""
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        pass
    try:
        tree = ET.parse(Path(get_package_share_directory(PACKAGE)) / "package.xml")
        return (tree.getroot().findtext("version") or "unknown").strip()
    except (LookupError, OSError, ET.ParseError, ValueError):
        return "unknown"


def _message_class(type_name: str) -> type:
    package, name = split_type_name(type_name)
    try:
        return getattr(import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError) as err:
        raise RecorderError(
            f"cannot import message type {type_name}: {err}; build the workspace "
            "(make build) and source tools/ros_env.sh") from None


def _session_name_problem(value: Any) -> str | None:
    text = str(value)
    if not text or text in (".", "..") or "/" in text or os.sep in text:
        return "must be a single directory name (no '/'), not empty"
    return None


@dataclass
class _Pending:
    topic: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


class _WriteQueue:
    """FIFO of messages bounded in bytes; full, it drops the oldest message (counted)."""

    def __init__(self, limit_bytes: int) -> None:
        self._limit = limit_bytes
        self._items: deque[_Pending] = deque()
        self._bytes = 0
        self._closed = False
        self._cv = threading.Condition()
        self.dropped: dict[str, int] = {}

    def put(self, item: _Pending) -> int:
        """Append; return how many old messages were dropped to make room."""
        dropped = 0
        with self._cv:
            while self._items and self._bytes + len(item.data) > self._limit:
                old = self._items.popleft()
                self._bytes -= len(old.data)
                self.dropped[old.topic] = self.dropped.get(old.topic, 0) + 1
                dropped += 1
            self._items.append(item)
            self._bytes += len(item.data)
            self._cv.notify()
        return dropped

    def take_all(self, timeout: float) -> tuple[list[_Pending], bool]:
        """Wait up to ``timeout`` s for messages; return them all and whether closed."""
        with self._cv:
            if not self._items and not self._closed:
                self._cv.wait(timeout=timeout)
            items = list(self._items)
            self._items.clear()
            self._bytes = 0
            return items, self._closed

    def close(self) -> None:
        """Let the consumer finish once the queue is empty."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()


class RecorderNode(Node):
    """Records the session topics into ``<bags_dir>/<session_name>`` (rosbag2 MCAP)."""

    def __init__(self) -> None:
        super().__init__("recorder", namespace=topics.NAMESPACE)
        self._checks = ParameterChecks(self)
        self._checks.add("session_name", _session_name_problem)
        self._checks.add("bags_dir", lambda v: None if str(v) else "must not be empty")
        self._checks.add("topics", self._topics_problem)
        p = self.declare_parameter
        p("topics", list(SESSION_TOPICS), descriptor(
            "Topics to record, relative to the namespace or absolute; each must be one of "
            f"the known session topics ({', '.join(TOPIC_TABLE)})", read_only=True))
        p("record_outputs", True, descriptor(
            "Also record the reconstruction outputs (normals, depth, points, normal_map); "
            "false leaves these heavy topics out", read_only=True))
        p("bags_dir", "bags", descriptor(
            "Directory the session bag directory is created in (created if missing)",
            read_only=True))
        p("session_name", default_session_name(), descriptor(
            "Name of the bag directory (and of its MCAP file, <name>_0.mcap); must not "
            "exist yet", read_only=True))
        p("chunk_size", DEFAULT_CHUNK_SIZE, descriptor(
            "Uncompressed bytes per MCAP chunk: the compression unit and the most a killed "
            "recorder loses", min_value=64 * 1024, max_value=512 * 1024 * 1024, integer=True,
            read_only=True))
        p("flush_period", 2.0, descriptor(
            "Seconds after which an open MCAP chunk is written even if not full (bounds the "
            "loss on a crash in time); 0 writes chunks only when full",
            min_value=0.0, max_value=3600.0))
        p("queue_limit_mb", 512, descriptor(
            "Megabytes of messages waiting for the writer; beyond this the oldest are "
            "dropped (and counted)", min_value=1, max_value=65536, integer=True,
            read_only=True))
        p("history_depth", 50, descriptor(
            "Keep-last depth of the recorder's subscriptions: messages per topic DDS holds "
            "for the recorder while its executor is busy (a deeper reader history is "
            "compatible with every publisher; the publishers' own depth is kept in the bag's "
            "QoS metadata)", min_value=1, max_value=10000, integer=True, read_only=True))
        p("max_bagfile_size", 0, descriptor(
            "Bytes after which the bag goes on in a new MCAP file <session_name>_<n>.mcap "
            "(rosbag2's max_bagfile_size); 0 = one file", min_value=0,
            max_value=2**50, integer=True, read_only=True))
        p("max_bagfile_duration", 0, descriptor(
            "Seconds of messages after which the bag goes on in a new MCAP file (rosbag2's "
            "max_bagfile_duration); 0 = no limit", min_value=0, max_value=10**7,
            integer=True, read_only=True))
        p("bags_dir_limit_mb", 0, descriptor(
            "Megabytes the sessions in bags_dir may add up to; beyond it the oldest whole "
            "sessions are removed, never the one being recorded; 0 = no limit",
            min_value=0, max_value=2**30, integer=True, read_only=True))

        self._checks.refuse_unknown_overrides(self)

        self._shutdown_logger = rclpy.logging.get_logger(f"{self.get_logger().name}.bag")
        self._use_sim_time = bool(self.get_parameter("use_sim_time").value)
        # Everything that can fail on bad input happens before the bag directory is made.
        self._record = self._resolve_topics()
        for type_name in sorted({spec.type_name for spec in self._record.values()}):
            load_message_definition(type_name)  # fail now, not at the first message
        classes = {topic: _message_class(spec.type_name) for topic, spec in self._record.items()}
        self._bags_dir = Path(str(self.get_parameter("bags_dir").value))
        bag_path = self._bags_dir / str(self.get_parameter("session_name").value)
        self._limit_bytes = int(self.get_parameter("bags_dir_limit_mb").value) * MiB
        self._bag = SessionBagWriter(
            bag_path, chunk_size=int(self.get_parameter("chunk_size").value),
            ros_distro=os.environ.get("ROS_DISTRO") or "jazzy",
            max_bagfile_size=int(self.get_parameter("max_bagfile_size").value),
            max_bagfile_duration_ns=int(self.get_parameter("max_bagfile_duration").value)
            * NS_PER_S)
        self._finished = False
        self._received = 0
        self._write_errors: dict[str, int] = {}
        self._unrecordable_messages: dict[str, int] = {}
        self._gaps = SequenceGaps()
        self._last_loss = -1.0  # monotonic time of the last message not written
        self._last_write_error = -1.0
        self._retention = RetentionResult()
        self._sessions_removed = 0
        self._enforce_retention()  # room for this session before it starts
        self._queue = _WriteQueue(int(self.get_parameter("queue_limit_mb").value) * 1024 * 1024)
        self._subscriptions_made: list[Any] = []
        self._registered: set[str] = set()  # topics added to the bag (callback thread only)
        self._unrecordable: set[str] = set()  # topics the bag refused (logged once)
        self._worker = threading.Thread(target=self._work, name="recorder_writer")
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_timer(1.0, self._publish_diagnostics)

        self._bag.start()
        try:
            self._bag.add_metadata("fingerps.software", self._software_record())
            self._bag.add_metadata("fingerps.recorder.parameters", self._parameters_record())
            self._worker.start()
            depth = int(self.get_parameter("history_depth").value)
            for topic, spec in self._record.items():
                self._subscriptions_made.append(self.create_subscription(
                    classes[topic], topic, functools.partial(self._on_message, topic),
                    _deeper(spec.qos, depth), raw=True))
        except BaseException:
            self.finish_bag()
            raise
        self.get_logger().info(
            f"recording {len(self._record)} topics into {self._bag.path.resolve()}: "
            f"{', '.join(self._record)}")

    # ------------------------------------------------------------------ set-up
    def _topics_problem(self, value: Any) -> str | None:
        unknown = [t for t in value if self._known_topic(t) is None]
        if unknown:
            return (f"unknown topics {unknown}; the recorder knows {', '.join(TOPIC_TABLE)} "
                    "(relative to its namespace)")
        return None

    def _known_topic(self, name: str) -> str | None:
        """The table key a (relative or absolute) topic name resolves to, or None."""
        try:
            resolved = self.resolve_topic_name(name)
        except Exception:  # rclpy raises several kinds for bad names
            return None
        for key in TOPIC_TABLE:
            if self.resolve_topic_name(key) == resolved:
                return key
        return None

    def _resolve_topics(self) -> dict[str, RecordedTopic]:
        """Fully qualified name -> table entry of every topic to record."""
        requested = list(self.get_parameter("topics").value or [])
        keep_outputs = bool(self.get_parameter("record_outputs").value)
        chosen: dict[str, RecordedTopic] = {}
        for name in requested:
            key = self._known_topic(name)
            if key is None:  # only reachable if the on-set check was bypassed
                raise RecorderError(f"unknown topic {name!r}; known: {', '.join(TOPIC_TABLE)}")
            if key in OUTPUT_TOPICS and not keep_outputs:
                continue
            chosen[self.resolve_topic_name(key)] = TOPIC_TABLE[key]
        if not chosen:
            raise RecorderError(
                "nothing to record: 'topics' is empty (or holds only outputs and "
                "record_outputs is false); give at least one topic")
        return chosen

    def _software_record(self) -> dict[str, str]:
        return {
            "package": PACKAGE,
            "version": software_version(),
            "node": self.get_fully_qualified_name(),
            "ros_distro": os.environ.get("ROS_DISTRO") or "jazzy",
            "rmw_implementation": get_rmw_implementation_identifier(),
            "python": platform.python_version(),
            "mcap": _dist_version("mcap"),
            "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        }

    def _parameters_record(self) -> dict[str, str]:
        record = {}
        parameters = self.get_parameters_by_prefix("")
        for name in sorted(parameters):
            value = parameters[name].value
            record[name] = value if isinstance(value, str) else json.dumps(
                list(value) if isinstance(value, (list, tuple)) else value)
        return record

    # ------------------------------------------------------------------ intake
    def _on_message(self, topic: str, data: bytes, info: dict[str, int]) -> None:
        """Subscription callback: stamp, register the topic once, enqueue. Nothing else.

        Log time is the receive time (the node clock's with use_sim_time), publish time the
        source time, as rosbag2 records them.
        """
        if self._use_sim_time:
            received = self.get_clock().now().nanoseconds
        else:
            received = int(info.get("received_timestamp", 0)) or time.time_ns()
        source = int(info.get("source_timestamp", 0))
        self._received += 1
        if self._gaps.observe(topic, info.get("publication_sequence_number"),
                              self.count_publishers(topic)):
            self._last_loss = time.monotonic()
            self.get_logger().warning(
                f"messages lost before the recorder took them: {self._gaps.lost} so far (the "
                "recorder's process is too slow or starved of CPU)", throttle_duration_sec=5.0)
        if topic not in self._registered and not self._add_topic(topic):
            self._unrecordable_messages[topic] = self._unrecordable_messages.get(topic, 0) + 1
            self._last_loss = time.monotonic()
            return
        dropped = self._queue.put(_Pending(topic, bytes(data), received, source))
        if dropped:
            self._last_loss = time.monotonic()
            self.get_logger().warning(
                f"the bag writer is behind: dropped {sum(self._queue.dropped.values())} "
                "messages so far (raise queue_limit_mb or record_outputs:=false)",
                throttle_duration_sec=5.0)
        self.get_logger().info(f"recording: {self._received} messages received",
                               throttle_duration_sec=30.0)

    def _add_topic(self, topic: str) -> bool:
        """Register a topic with the QoS its publishers offer (qos.py's if none is seen).

        Returns whether the topic can be recorded.
        """
        if topic in self._unrecordable:
            return False
        spec = self._record[topic]
        offered = [QosProfileFields.from_profile(info.qos_profile)
                   for info in self.get_publishers_info_by_topic(topic)]
        if not offered:
            offered = [QosProfileFields.from_profile(spec.qos)]
        try:
            self._bag.add_topic(topic, spec.type_name, offered_qos_yaml=qos_profiles_yaml(offered))
        except SessionBagError as err:
            self._unrecordable.add(topic)
            self.get_logger().error(f"not recording {topic}: {err}")
            return False
        self._registered.add(topic)
        return True

    # ------------------------------------------------------------------ writer thread
    def _work(self) -> None:
        last_flush = last_retention = time.monotonic()
        pieces = 0
        while True:
            items, closed = self._queue.take_all(timeout=0.2)
            for item in items:
                try:
                    self._bag.write(item.topic, item.data, log_time_ns=item.log_time_ns,
                                    publish_time_ns=item.publish_time_ns)
                except SessionBagError as err:
                    self._write_errors[item.topic] = self._write_errors.get(item.topic, 0) + 1
                    self._last_write_error = self._last_loss = time.monotonic()
                    self._shutdown_logger.error(f"{err}", throttle_duration_sec=5.0)
            finished = self._bag.pieces
            new_piece = len(finished) != pieces
            if new_piece:
                pieces = len(finished)
                self._shutdown_logger.info(
                    f"bag piece {finished[-1].path.name} finished ({finished[-1].message_count} "
                    f"messages, {finished[-1].size_bytes / MiB:.1f} MiB); going on in "
                    f"{self._bag.mcap_path.name}")
            if self._limit_bytes and (new_piece or
                                      time.monotonic() - last_retention >= RETENTION_PERIOD_S):
                self._enforce_retention()
                last_retention = time.monotonic()
            period = float(self.get_parameter("flush_period").value)
            if period > 0.0 and time.monotonic() - last_flush >= period:
                try:
                    self._bag.flush()
                except SessionBagError as err:
                    self._shutdown_logger.error(f"{err}", throttle_duration_sec=5.0)
                last_flush = time.monotonic()
            if closed and not items:
                return

    # ------------------------------------------------------------------ exit
    def finish_bag(self) -> None:
        """Stop intake, drain the queue, finish the bag and log what it holds (idempotent)."""
        if self._finished:
            return
        self._finished = True
        for subscription in self._subscriptions_made:
            self.destroy_subscription(subscription)
        self._queue.close()
        if self._worker.ident is not None:  # started
            self._worker.join()
        log = self.get_logger() if self.context.ok() else self._shutdown_logger
        not_written = self.not_written()
        record = {topic: json.dumps(reasons) for topic, reasons in not_written.items()}
        try:
            if self._bag.is_open:
                self._bag.add_metadata("fingerps.recorder.not_written", record)
            self._bag.set_custom_data("fingerps.not_written", json.dumps(not_written))
            summary = self._bag.finish()
        except SessionBagError as err:
            log.error(str(err))
            return
        counts = ", ".join(f"{topic}: {count}" for topic, count in summary.message_counts.items())
        pieces = f" in {len(summary.pieces)} pieces" if len(summary.pieces) > 1 else ""
        log.info(f"bag {summary.path.resolve()}: {summary.message_count} messages{pieces}"
                 f"{' (' + counts + ')' if counts else ''}")
        if not_written:
            total = sum(sum(reasons.values()) for reasons in not_written.values())
            log.warning(f"{total} messages subscribed to were not written: {not_written}")

    def not_written(self) -> dict[str, dict[str, int]]:
        """Messages subscribed to and not written, per topic and reason (no zero entries)."""
        reasons = {"lost_before_recorder": self._gaps.lost,
                   "dropped_writer_behind": self._queue.dropped,
                   "write_errors": self._write_errors,
                   "unrecordable": self._unrecordable_messages}
        table: dict[str, dict[str, int]] = {}
        for reason, per_topic in reasons.items():
            for topic, count in dict(per_topic).items():
                if count:
                    table.setdefault(topic, {})[reason] = count
        return table

    def _enforce_retention(self) -> None:
        """Keep bags_dir within bags_dir_limit_mb (oldest sessions first), log what went."""
        if not self._limit_bytes:
            return
        result = enforce_limit(self._bags_dir, self._limit_bytes, keep=self._bag.path)
        self._retention = result
        self._sessions_removed += len(result.removed)
        for session in result.removed:
            self._shutdown_logger.warning(
                f"bags_dir_limit_mb: removed the oldest session {session.path} "
                f"({session.size_bytes / MiB:.1f} MiB)")
        for failure in result.failed:
            self._shutdown_logger.error(f"bags_dir_limit_mb: cannot remove {failure}",
                                        throttle_duration_sec=60.0)
        if result.total_bytes > self._limit_bytes:
            self._shutdown_logger.warning(
                f"bags_dir {self._bags_dir} holds {result.total_bytes / MiB:.0f} MiB of "
                f"sessions, more than bags_dir_limit_mb {self._limit_bytes // MiB}, with no "
                "older session left to remove (this session alone is larger; set "
                "max_bagfile_size and a larger limit, or record_outputs:=false)",
                throttle_duration_sec=60.0)

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        not_written = self.not_written()
        by_reason: dict[str, int] = {}
        for reasons in not_written.values():
            for reason, count in reasons.items():
                by_reason[reason] = by_reason.get(reason, 0) + count
        total = sum(by_reason.values())
        status = DiagnosticStatus(name=f"{self.get_name()}: recording")
        if self._last_write_error >= 0 and now - self._last_write_error < HEALTH_WINDOW_S:
            status.level = DiagnosticStatus.ERROR
            status.message = "writing the bag fails (see the log)"
        elif self._last_loss >= 0 and now - self._last_loss < HEALTH_WINDOW_S:
            status.level = DiagnosticStatus.WARN
            status.message = f"{total} messages not written so far"
        elif self._limit_bytes and self._retention.total_bytes > self._limit_bytes:
            status.level = DiagnosticStatus.WARN
            status.message = "bags_dir is over bags_dir_limit_mb with nothing left to remove"
        else:
            status.level = DiagnosticStatus.OK
            status.message = "ok"
        written = sum(self._bag.message_counts.values())
        status.values = [
            KeyValue(key="messages_received", value=str(self._received)),
            KeyValue(key="messages_written", value=str(written)),
            KeyValue(key="not_written", value=str(total)),
            *(KeyValue(key=reason, value=str(by_reason.get(reason, 0)))
              for reason in ("lost_before_recorder", "dropped_writer_behind", "write_errors",
                             "unrecordable")),
            KeyValue(key="not_written_by_topic", value=json.dumps(not_written)),
            KeyValue(key="bag", value=str(self._bag.path)),
            KeyValue(key="bag_pieces", value=str(len(self._bag.pieces) + self._bag.is_open)),
            KeyValue(key="bag_bytes", value=str(self._bag.bytes_written)),
            KeyValue(key="bags_dir_bytes", value=str(self._retention.total_bytes)),
            KeyValue(key="bags_dir_limit_bytes", value=str(self._limit_bytes)),
            KeyValue(key="sessions_removed", value=str(self._sessions_removed)),
        ]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)

    def destroy_node(self) -> None:
        """Finish the bag (so SIGINT and SIGTERM leave a valid bag), then destroy the node."""
        self.finish_bag()
        super().destroy_node()


def _deeper(profile: QoSProfile, depth: int) -> QoSProfile:
    """The topic's profile with a keep-last depth of at least ``depth``."""
    return QoSProfile(history=profile.history, depth=max(profile.depth, depth),
                      reliability=profile.reliability, durability=profile.durability,
                      deadline=profile.deadline, lifespan=profile.lifespan,
                      liveliness=profile.liveliness,
                      liveliness_lease_duration=profile.liveliness_lease_duration)


def _dist_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return ""


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon recorder_node``; returns the exit code.

    Exit code 2 with one line (no traceback) when the recorder cannot start, e.g. a
    bags_dir that cannot be created or a bag directory that already exists.
    """
    return run_node(RecorderNode, args=args, name="recorder_node",
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
