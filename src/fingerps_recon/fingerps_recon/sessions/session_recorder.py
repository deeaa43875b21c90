"""The recording session: serialized messages in, a split rosbag2 MCAP bag out.

`SessionRecorder` is what recorder_node calls: the node subscribes and converts, this class
writes. It holds the bag (`sessions.session_bag.SessionBagWriter`, split into pieces by size
and duration as rosbag2 does), keeps ``bags_dir`` under its limit (`sessions.session_retention`:
at start, at each new piece and every ``RETENTION_PERIOD_S`` seconds, never the session being
recorded), and says how healthy the recording is (`SessionRecorder.health`).

Nothing is lost silently. A message the recorder subscribed to and did not write is counted
per topic and reason: ``lost_before_recorder`` (skipped in the publisher's sequence numbers,
`sessions.sequence_gaps`: DDS overwrote or missed it before the recorder took it),
``dropped_writer_behind`` (the write queue was full), ``write_errors``, ``unrecordable``
(the bag refused the topic). The counts are in `SessionRecorder.health` and in the finished
bag: metadata.yaml's ``custom_data`` ``fingerps.not_written`` and the MCAP metadata record
``fingerps.recorder.not_written``.

Threads: `SessionRecorder.receive` (the subscription callbacks) only counts the message and
appends it to a queue (on a topic's first message it also registers the topic, with the
publishers' QoS as the graph shows them, as rosbag2 does). A writer thread takes the
messages from the queue, writes them, and closes the open MCAP chunk every flush period, so
compression never blocks intake. The queue is bounded in bytes (`sessions.write_queue`) and
drops the oldest message when full; drops are counted, logged (throttled) and reported at
the end. `SessionRecorder.finish` drains the queue and finishes the bag.

No rclpy Node here: the node passes in its logger and what it asks the graph.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fingerps_recon.errors import SessionBagError
from fingerps_recon.sessions.rosbag2_qos import QosProfileFields, qos_profiles_yaml
from fingerps_recon.sessions.sequence_gaps import SequenceGaps
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_recon.sessions.session_retention import RetentionResult, enforce_limit
from fingerps_recon.sessions.session_topics import RecordedTopic
from fingerps_recon.sessions.write_queue import PendingMessage, WriteQueue

RETENTION_PERIOD_S = 10.0
"""How often the writer thread checks the bags_dir limit between pieces."""
HEALTH_WINDOW_S = 10.0
"""The health warns while messages went unwritten within this many seconds."""
MiB = 1024 * 1024
NOT_WRITTEN_REASONS = ("lost_before_recorder", "dropped_writer_behind", "write_errors",
                       "unrecordable")
OK, WARN, ERROR = 0, 1, 2
"""Health levels, as diagnostic_msgs/DiagnosticStatus numbers them."""


@dataclass(frozen=True)
class RecorderHealth:
    """The recording's state for /diagnostics."""

    level: int
    """`OK`, `WARN` or `ERROR`."""
    message: str
    values: dict[str, str]
    """Key -> value, in the order they are published."""


class SessionRecorder:
    """Writes the messages of the chosen topics into one session bag.

    Parameters
    ----------
    bag : SessionBagWriter
        The bag to write, not started yet.
    record : Mapping[str, RecordedTopic]
        Fully qualified topic name -> its type and QoS.
    bags_dir : Path
        The directory of the session bags (``bags_dir_limit_bytes`` applies to it).
    bags_dir_limit_bytes : int
        Bytes the sessions in ``bags_dir`` may add up to; 0 = no limit.
    queue_limit_bytes : int
        Bytes of messages waiting for the writer before the oldest are dropped.
    flush_period_s : Callable[[], float]
        Seconds after which an open chunk is written (read at every round; 0 = when full).
    publishers : Callable[[str], int]
        Publishers on a topic now (the graph's count).
    offered_qos : Callable[[str], list[QosProfileFields]]
        The QoS of a topic's publishers now (the graph's).
    logger : Any
        The node's logger, used by intake (rclpy's: ``throttle_duration_sec=``).
    writer_logger : Any
        The logger of the writer thread and of shutdown.
    """

    def __init__(self, bag: SessionBagWriter, record: Mapping[str, RecordedTopic], *,
                 bags_dir: Path, bags_dir_limit_bytes: int, queue_limit_bytes: int,
                 flush_period_s: Callable[[], float], publishers: Callable[[str], int],
                 offered_qos: Callable[[str], list[QosProfileFields]], logger: Any,
                 writer_logger: Any) -> None:
        self._bag = bag
        self._record = dict(record)
        self._bags_dir = bags_dir
        self._limit_bytes = bags_dir_limit_bytes
        self._flush_period_s = flush_period_s
        self._publishers = publishers
        self._offered_qos = offered_qos
        self._log = logger
        self._writer_log = writer_logger
        self._finished = False
        self._received = 0
        self._write_errors: dict[str, int] = {}
        self._unrecordable_messages: dict[str, int] = {}
        self._gaps = SequenceGaps()
        self._last_loss = -1.0  # monotonic time of the last message not written
        self._last_write_error = -1.0
        self._retention = RetentionResult()
        self._sessions_removed = 0
        self._queue = WriteQueue(queue_limit_bytes)
        self._registered: set[str] = set()  # topics added to the bag (callback thread only)
        self._unrecordable: set[str] = set()  # topics the bag refused (logged once)
        self._worker = threading.Thread(target=self._work, name="recorder_writer")

    def start(self, metadata: Mapping[str, Mapping[str, str]]) -> None:
        """Make room in bags_dir, open the bag, write its metadata records, start writing.

        A failure after the bag is opened finishes it (so it is valid) and is raised.
        """
        self.enforce_retention()  # room for this session before it starts
        self._bag.start()
        try:
            for name, record in metadata.items():
                self._bag.add_metadata(name, dict(record))
            self._worker.start()
        except BaseException:
            self.finish()
            raise

    # ------------------------------------------------------------------ intake
    def receive(self, topic: str, data: bytes, *, log_time_ns: int, publish_time_ns: int,
                sequence: int | None) -> None:
        """Count a message, register its topic once, enqueue it. Nothing else.

        ``sequence`` is the publisher's sequence number (None or 0 when not known).
        """
        self._received += 1
        if self._gaps.observe(topic, sequence, self._publishers(topic)):
            self._last_loss = time.monotonic()
            self._log.warning(
                f"messages lost before the recorder took them: {self._gaps.lost} so far (the "
                "recorder's process is too slow or starved of CPU)", throttle_duration_sec=5.0)
        if topic not in self._registered and not self._add_topic(topic):
            self._unrecordable_messages[topic] = self._unrecordable_messages.get(topic, 0) + 1
            self._last_loss = time.monotonic()
            return
        dropped = self._queue.put(PendingMessage(topic, bytes(data), log_time_ns,
                                                 publish_time_ns))
        if dropped:
            self._last_loss = time.monotonic()
            self._log.warning(
                f"the bag writer is behind: dropped {sum(self._queue.dropped.values())} "
                "messages so far (raise queue_limit_mb or record_outputs:=false)",
                throttle_duration_sec=5.0)
        self._log.info(f"recording: {self._received} messages received",
                       throttle_duration_sec=30.0)

    def _add_topic(self, topic: str) -> bool:
        """Register a topic with the QoS its publishers offer (qos.py's if none is seen).

        Returns whether the topic can be recorded.
        """
        if topic in self._unrecordable:
            return False
        spec = self._record[topic]
        offered = self._offered_qos(topic) or [QosProfileFields.from_profile(spec.qos)]
        try:
            self._bag.add_topic(topic, spec.type_name, offered_qos_yaml=qos_profiles_yaml(offered))
        except SessionBagError as err:
            self._unrecordable.add(topic)
            self._log.error(f"not recording {topic}: {err}")
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
                    self._writer_log.error(f"{err}", throttle_duration_sec=5.0)
            finished = self._bag.pieces
            new_piece = len(finished) != pieces
            if new_piece:
                pieces = len(finished)
                self._writer_log.info(
                    f"bag piece {finished[-1].path.name} finished ({finished[-1].message_count} "
                    f"messages, {finished[-1].size_bytes / MiB:.1f} MiB); going on in "
                    f"{self._bag.mcap_path.name}")
            if self._limit_bytes and (new_piece or
                                      time.monotonic() - last_retention >= RETENTION_PERIOD_S):
                self.enforce_retention()
                last_retention = time.monotonic()
            period = float(self._flush_period_s())
            if period > 0.0 and time.monotonic() - last_flush >= period:
                try:
                    self._bag.flush()
                except SessionBagError as err:
                    self._writer_log.error(f"{err}", throttle_duration_sec=5.0)
                last_flush = time.monotonic()
            if closed and not items:
                return

    # ------------------------------------------------------------------ end
    def finish(self, log: Any = None) -> None:
        """Drain the queue, finish the bag and log what it holds to ``log`` (the node's
        logger when None); idempotent. Stop the intake first."""
        if self._finished:
            return
        self._finished = True
        log = log or self._log
        self._queue.close()
        if self._worker.ident is not None:  # started
            self._worker.join()
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
        reasons = dict(zip(NOT_WRITTEN_REASONS, (
            self._gaps.lost, self._queue.dropped, self._write_errors,
            self._unrecordable_messages), strict=True))
        table: dict[str, dict[str, int]] = {}
        for reason, per_topic in reasons.items():
            for topic, count in dict(per_topic).items():
                if count:
                    table.setdefault(topic, {})[reason] = count
        return table

    def enforce_retention(self) -> None:
        """Keep bags_dir within its limit (oldest sessions first), log what went."""
        if not self._limit_bytes:
            return
        result = enforce_limit(self._bags_dir, self._limit_bytes, keep=self._bag.path)
        self._retention = result
        self._sessions_removed += len(result.removed)
        for session in result.removed:
            self._writer_log.warning(
                f"bags_dir_limit_mb: removed the oldest session {session.path} "
                f"({session.size_bytes / MiB:.1f} MiB)")
        for failure in result.failed:
            self._writer_log.error(f"bags_dir_limit_mb: cannot remove {failure}",
                                   throttle_duration_sec=60.0)
        if result.total_bytes > self._limit_bytes:
            self._writer_log.warning(
                f"bags_dir {self._bags_dir} holds {result.total_bytes / MiB:.0f} MiB of "
                f"sessions, more than bags_dir_limit_mb {self._limit_bytes // MiB}, with no "
                "older session left to remove (this session alone is larger; set "
                "max_bagfile_size and a larger limit, or record_outputs:=false)",
                throttle_duration_sec=60.0)

    # ------------------------------------------------------------------ health
    def health(self) -> RecorderHealth:
        """Level, message and figures of the recording now."""
        now = time.monotonic()
        not_written = self.not_written()
        by_reason: dict[str, int] = {}
        for reasons in not_written.values():
            for reason, count in reasons.items():
                by_reason[reason] = by_reason.get(reason, 0) + count
        total = sum(by_reason.values())
        if self._last_write_error >= 0 and now - self._last_write_error < HEALTH_WINDOW_S:
            level, message = ERROR, "writing the bag fails (see the log)"
        elif self._last_loss >= 0 and now - self._last_loss < HEALTH_WINDOW_S:
            level, message = WARN, f"{total} messages not written so far"
        elif self._limit_bytes and self._retention.total_bytes > self._limit_bytes:
            level, message = WARN, "bags_dir is over bags_dir_limit_mb with nothing left to remove"
        else:
            level, message = OK, "ok"
        values = {
            "messages_received": str(self._received),
            "messages_written": str(sum(self._bag.message_counts.values())),
            "not_written": str(total),
            **{reason: str(by_reason.get(reason, 0)) for reason in NOT_WRITTEN_REASONS},
            "not_written_by_topic": json.dumps(not_written),
            "bag": str(self._bag.path),
            "bag_pieces": str(len(self._bag.pieces) + self._bag.is_open),
            "bag_bytes": str(self._bag.bytes_written),
            "bags_dir_bytes": str(self._retention.total_bytes),
            "bags_dir_limit_bytes": str(self._limit_bytes),
            "sessions_removed": str(self._sessions_removed),
        }
        return RecorderHealth(level, message, values)
