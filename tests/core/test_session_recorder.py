"""Tests of the recording session without a ROS graph: fingerps_recon.sessions.session_recorder
(intake, writer thread, pieces, retention, not-written counts, health), write_queue,
session_topics and session_metadata.

The graph is two plain functions (publishers, offered QoS); the logger records its lines.
"""

from __future__ import annotations

import json
import os
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from fingerps_recon.errors import RecorderError, SessionBagError
from fingerps_recon.sessions.bag_reader import SessionBagReader
from fingerps_recon.sessions.rosbag2_qos import QosProfileFields
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_recon.sessions.session_metadata import (
    default_session_name,
    parameters_record,
    session_name_problem,
    software_record,
)
from fingerps_recon.sessions.session_recorder import (
    ERROR,
    OK,
    WARN,
    SessionRecorder,
)
from fingerps_recon.sessions.session_topics import (
    OUTPUT_TOPICS,
    SESSION_TOPICS,
    TOPIC_TABLE,
    RecordedTopic,
    choose_topics,
    topics_problem,
)
from fingerps_recon.sessions.write_queue import PendingMessage, WriteQueue
from fingerps_ros import qos

T0 = 1_700_000_000_000_000_000
CHATTER = "/fingerps/chatter"
BROKEN = "/fingerps/broken"
MiB = 1024 * 1024


class RecordingLogger:
    """A logger that keeps its lines as (level, text)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str, **_: Any) -> None:
        self.lines.append(("info", message))

    def warning(self, message: str, **_: Any) -> None:
        self.lines.append(("warning", message))

    def error(self, message: str, **_: Any) -> None:
        self.lines.append(("error", message))

    def text(self, level: str) -> str:
        return "\n".join(t for lv, t in self.lines if lv == level)


def _message(i: int, size: int = 100) -> bytes:
    return serialize_message(String(data=f"{i:08d}" + "x" * size))


def _recorder(tmp_path: Path, *, record: dict[str, RecordedTopic] | None = None,
              publishers: int = 1, limit_bytes: int = 0, flush_s: float = 0.0,
              **bag_options: int) -> tuple[SessionRecorder, RecordingLogger, RecordingLogger]:
    log, writer_log = RecordingLogger(), RecordingLogger()
    bag = SessionBagWriter(tmp_path / "bags" / "session", chunk_size=64 * 1024, **bag_options)
    recorder = SessionRecorder(
        bag, record or {CHATTER: RecordedTopic("std_msgs/msg/String", qos.BURST_QOS)},
        bags_dir=tmp_path / "bags", bags_dir_limit_bytes=limit_bytes,
        queue_limit_bytes=64 * MiB, flush_period_s=lambda: flush_s,
        publishers=lambda _topic: publishers, offered_qos=lambda _topic: [],
        logger=log, writer_logger=writer_log)
    return recorder, log, writer_log


def _metadata(bag_dir: Path) -> dict:
    return yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def test_messages_are_written_into_a_bag_with_its_metadata_records(tmp_path: Path) -> None:
    recorder, log, _ = _recorder(tmp_path)
    recorder.start({"fingerps.software": {"package": "fingerps_recon"}})
    for i in range(5):
        recorder.receive(CHATTER, _message(i), log_time_ns=T0 + i, publish_time_ns=T0 + i - 1,
                         sequence=i + 1)
    recorder.finish()
    recorder.finish()  # idempotent

    bag_dir = tmp_path / "bags" / "session"
    reader = SessionBagReader(bag_dir)
    assert [m.deserialize().data[:8] for m in reader.messages()] == [f"{i:08d}" for i in range(5)]
    assert recorder.not_written() == {}
    assert json.loads(_metadata(bag_dir)["custom_data"]["fingerps.not_written"]) == {}
    with open(bag_dir / "session_0.mcap", "rb") as stream:
        records = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert records["fingerps.software"] == {"package": "fingerps_recon"}
    assert records["fingerps.recorder.not_written"] == {}
    assert f"bag {bag_dir.resolve()}: 5 messages ({CHATTER}: 5)" in log.text("info")
    assert "recording: 5 messages received" in log.text("info")

    health = recorder.health()
    assert (health.level, health.message) == (OK, "ok")
    assert list(health.values) == [
        "messages_received", "messages_written", "not_written", "lost_before_recorder",
        "dropped_writer_behind", "write_errors", "unrecordable", "not_written_by_topic", "bag",
        "bag_pieces", "bag_bytes", "bags_dir_bytes", "bags_dir_limit_bytes", "sessions_removed"]
    assert health.values["messages_received"] == health.values["messages_written"] == "5"


def test_gaps_and_unrecordable_topics_are_counted_per_topic_and_reason(
        tmp_path: Path) -> None:
    record = {CHATTER: RecordedTopic("std_msgs/msg/String", qos.BURST_QOS),
              BROKEN: RecordedTopic("no_such_package/msg/Nothing", qos.BURST_QOS)}
    recorder, log, _ = _recorder(tmp_path, record=record)
    recorder.start({})
    for sequence in (1, 2, 5, 6):  # 3 and 4 lost before the recorder
        recorder.receive(CHATTER, _message(sequence), log_time_ns=T0 + sequence,
                         publish_time_ns=T0, sequence=sequence)
    for i in range(2):
        recorder.receive(BROKEN, b"\0\1\0\0", log_time_ns=T0 + i, publish_time_ns=T0,
                         sequence=None)

    expected = {CHATTER: {"lost_before_recorder": 2}, BROKEN: {"unrecordable": 2}}
    assert recorder.not_written() == expected
    health = recorder.health()
    assert (health.level, health.message) == (WARN, "4 messages not written so far")
    assert health.values["lost_before_recorder"] == "2"
    assert health.values["unrecordable"] == "2"
    assert json.loads(health.values["not_written_by_topic"]) == expected
    assert "messages lost before the recorder took them" in log.text("warning")
    assert log.text("error").count(f"not recording {BROKEN}") == 1  # logged once

    recorder.finish()
    meta = _metadata(tmp_path / "bags" / "session")
    assert json.loads(meta["custom_data"]["fingerps.not_written"]) == expected
    assert "4 messages subscribed to were not written" in log.text("warning")


def test_several_publishers_count_no_gaps(tmp_path: Path) -> None:
    recorder, _, _ = _recorder(tmp_path, publishers=2)
    recorder.start({})
    for sequence in (1, 7, 3):
        recorder.receive(CHATTER, _message(sequence), log_time_ns=T0 + sequence,
                         publish_time_ns=T0, sequence=sequence)
    recorder.finish()
    assert recorder.not_written() == {}


class _FullDiskBag(SessionBagWriter):
    def write(self, topic: str, data: bytes, **_: int) -> None:
        raise SessionBagError("no space left on the device")


def test_write_errors_make_the_health_an_error(tmp_path: Path) -> None:
    log, writer_log = RecordingLogger(), RecordingLogger()
    recorder = SessionRecorder(
        _FullDiskBag(tmp_path / "session"),
        {CHATTER: RecordedTopic("std_msgs/msg/String", qos.BURST_QOS)},
        bags_dir=tmp_path, bags_dir_limit_bytes=0, queue_limit_bytes=MiB,
        flush_period_s=lambda: 0.0, publishers=lambda _t: 1,
        offered_qos=lambda _t: [QosProfileFields.from_profile(qos.BURST_QOS)],
        logger=log, writer_logger=writer_log)
    recorder.start({})
    for i in range(3):
        recorder.receive(CHATTER, _message(i), log_time_ns=T0 + i, publish_time_ns=T0,
                         sequence=i + 1)
    recorder.finish()
    assert recorder.not_written() == {CHATTER: {"write_errors": 3}}
    health = recorder.health()
    assert (health.level, health.message) == (ERROR, "writing the bag fails (see the log)")
    assert "no space left on the device" in writer_log.text("error")


def test_pieces_are_logged_and_old_sessions_removed(tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    old = bags / "old_session"
    old.mkdir(parents=True)
    (old / "old_session_0.mcap").write_bytes(bytes(2 * MiB))
    os.utime(old / "old_session_0.mcap", (1_600_000_000, 1_600_000_000))
    recorder, log, writer_log = _recorder(tmp_path, limit_bytes=MiB,
                                          max_bagfile_size=64 * 1024)
    recorder.start({})
    assert not old.exists()
    assert f"removed the oldest session {old}" in writer_log.text("warning")
    for i in range(40):
        recorder.receive(CHATTER, serialize_message(String(data=os.urandom(5000).hex())),
                         log_time_ns=T0 + i, publish_time_ns=T0, sequence=i + 1)
    recorder.finish()
    meta = _metadata(bags / "session")
    assert len(meta["relative_file_paths"]) >= 2
    # A round of the writer may finish several pieces; it names the last.
    assert re.search(r"bag piece session_\d+\.mcap finished \(\d+ messages, [0-9.]+ MiB\); "
                     r"going on in session_\d+\.mcap", writer_log.text("info"))
    assert f"in {len(meta['relative_file_paths'])} pieces" in log.text("info")
    assert recorder.health().values["sessions_removed"] == "1"


def test_a_session_alone_over_the_limit_warns(tmp_path: Path) -> None:
    recorder, _, writer_log = _recorder(tmp_path, limit_bytes=1)
    recorder.start({})
    recorder.receive(CHATTER, _message(1, size=5000), log_time_ns=T0, publish_time_ns=T0,
                     sequence=1)
    recorder.finish()
    recorder.enforce_retention()
    assert "with no older session left to remove" in writer_log.text("warning")
    health = recorder.health()
    assert (health.level, health.message) == (
        WARN, "bags_dir is over bags_dir_limit_mb with nothing left to remove")


def test_the_write_queue_drops_the_oldest_when_full() -> None:
    queue = WriteQueue(limit_bytes=10)
    assert queue.put(PendingMessage("/a", bytes(4), 1, 1)) == 0
    assert queue.put(PendingMessage("/b", bytes(4), 2, 2)) == 0
    assert queue.put(PendingMessage("/b", bytes(8), 3, 3)) == 2
    assert queue.dropped == {"/a": 1, "/b": 1}
    items, closed = queue.take_all(timeout=0.0)
    assert [i.log_time_ns for i in items] == [3] and not closed
    queue.close()
    assert queue.take_all(timeout=1.0) == ([], True)


def _resolve(name: str) -> str:
    if not name or " " in name:
        raise ValueError(name)
    return name if name.startswith("/") else f"/fingerps/{name}"


def test_topics_are_chosen_from_the_table() -> None:
    chosen = choose_topics(SESSION_TOPICS, record_outputs=True, resolve=_resolve)
    assert list(chosen) == [f"/fingerps/{t}" for t in SESSION_TOPICS]
    lean = choose_topics(SESSION_TOPICS, record_outputs=False, resolve=_resolve)
    assert set(lean) == {f"/fingerps/{t}" for t in SESSION_TOPICS if t not in OUTPUT_TOPICS}
    assert choose_topics(["/fingerps/burst"], record_outputs=True, resolve=_resolve) == {
        "/fingerps/burst": TOPIC_TABLE["burst"]}
    assert topics_problem(["burst", "/fingerps/points"], _resolve) is None
    assert "unknown topics ['nope', 'bad name']" in topics_problem(["nope", "bad name"],
                                                                   _resolve)
    with pytest.raises(RecorderError, match="nothing to record"):
        choose_topics(["points"], record_outputs=False, resolve=_resolve)
    with pytest.raises(RecorderError, match="unknown topic 'nope'"):
        choose_topics(["nope"], record_outputs=True, resolve=_resolve)
    deeper = TOPIC_TABLE["burst"].subscription_qos(500)
    assert deeper.depth == 500 and deeper.reliability == qos.BURST_QOS.reliability
    assert TOPIC_TABLE["burst"].subscription_qos(1).depth == qos.BURST_QOS.depth
    assert QosProfileFields.from_profile(deeper).durability == \
        QosProfileFields.from_profile(qos.BURST_QOS).durability


def test_session_metadata_records() -> None:
    assert default_session_name(datetime(2025, 1, 31, 12, 0, 0, tzinfo=UTC)) == \
        "fingerps_20250131T120000Z"
    assert session_name_problem("a_session") is None
    for bad in ("", ".", "..", "a/b"):
        assert session_name_problem(bad)
    record = parameters_record({"topics": ["a", "b"], "bags_dir": "bags", "chunk_size": 7,
                                "record_outputs": True, "flush_period": 2.0})
    assert list(record) == sorted(record)
    assert record == {"bags_dir": "bags", "chunk_size": "7", "flush_period": "2.0",
                      "record_outputs": "true", "topics": '["a", "b"]'}
    software = software_record(node="/fingerps/recorder", rmw_implementation="rmw_x")
    assert software["package"] == "fingerps_recon" and software["node"] == "/fingerps/recorder"
    assert software["rmw_implementation"] == "rmw_x" and software["version"]
