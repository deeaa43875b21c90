"""Recovering an unfinished or damaged session bag into a valid one.

A recorder killed with SIGKILL (or stopped by a full disk) leaves an MCAP file without its
summary and a bag directory without metadata.yaml; a file cut by a copy or a disk error may
end in the middle of a chunk. `recover_bag` reads such a file record by record
(`fingerps_recon.mcap_records.scan_records`), keeps every schema, channel, message and
metadata record of every intact chunk before the first damage, writes them with
`SessionBagWriter` into a new bag directory (MCAP with summary + metadata.yaml), and says in a
`RecoveryReport` what was kept and what was lost.

Each channel keeps its original schema text, QoS metadata and type hash; the messages keep
their log and publish times and sequence numbers. The new bag gets one more metadata record,
``fingerps.recovery``, with the report.

No rclpy here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Attachment, Channel, Message, Metadata, Schema

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.mcap_records import (
    MAGIC,
    McapDamageError,
    ScanEnd,
    scan_records,
    summary_statistics,
)
from fingerps_recon.message_definition import MessageDefinition
from fingerps_recon.session_bag import (
    ROSBAG2_METADATA_RECORD,
    SessionBagError,
    SessionBagWriter,
)

RECOVERY_METADATA_RECORD = "fingerps.recovery"


class BagRecoveryError(FingerpsReconError):
    """A bag cannot be recovered (no MCAP file, destination taken, nothing readable)."""


@dataclass(frozen=True)
class RecoveryReport:
    """What `recover_bag` kept and lost.

    Attributes
    ----------
    source : Path
        The MCAP file read.
    destination : Path
        The new bag directory.
    file_size : int
        Bytes of the source file.
    kept_bytes : int
        Bytes of the source up to the end of the last intact record.
    message_counts : dict[str, int]
        Messages kept per topic.
    finished : bool
        Whether the source had its end-of-data record (it was finished, not killed).
    damage_offset : int or None
        Byte offset of the first damaged record; None when the file just ends (killed while
        idle between chunks) or was finished.
    damage_reason : str
        What was wrong there ("" without damage).
    lost_messages : int or None
        Messages lost, when the source's summary says how many it held; else None.
    lost_span_ns : tuple[int, int] or None
        Log-time range of the damaged chunk, when its header could be read.
    """

    source: Path
    destination: Path
    file_size: int
    kept_bytes: int
    message_counts: dict[str, int] = field(default_factory=dict)
    finished: bool = False
    damage_offset: int | None = None
    damage_reason: str = ""
    lost_messages: int | None = None
    lost_span_ns: tuple[int, int] | None = None

    @property
    def message_count(self) -> int:
        """Messages kept."""
        return sum(self.message_counts.values())

    @property
    def lost_bytes(self) -> int:
        """Bytes of the source after the last intact record."""
        return self.file_size - self.kept_bytes

    def describe(self) -> str:
        """A few lines for people: what was kept, where the damage is, what was lost."""
        lines = [f"recovered {self.source} -> {self.destination}"]
        counts = ", ".join(f"{t}: {n}" for t, n in self.message_counts.items()) or "none"
        lines.append(f"  kept   : {self.message_count} messages ({counts}); "
                     f"{self.kept_bytes} of {self.file_size} bytes")
        if self.damage_offset is not None:
            lines.append(f"  damage : at byte offset {self.damage_offset}: {self.damage_reason}")
        elif self.finished:
            lines.append("  damage : none (the file was finished; its summary was rebuilt)")
        else:
            lines.append(f"  damage : none; the file ends at byte offset {self.kept_bytes} "
                         "without its summary (the writer was killed between chunks; what it "
                         "had not yet written - at most one chunk or flush_period - never "
                         "reached the file)")
        lost = (f"{self.lost_messages} messages" if self.lost_messages is not None
                else "an unknown number of messages" if self.lost_bytes else "no messages")
        span = ""
        if self.lost_span_ns is not None:
            start, end = self.lost_span_ns
            span = f", logged {start / 1e9:.3f} .. {end / 1e9:.3f} s (epoch)"
        lines.append(f"  lost   : {lost}, {self.lost_bytes} bytes{span}")
        return "\n".join(lines)


def find_mcap(source: str | os.PathLike[str]) -> Path:
    """The MCAP file of a bag: ``source`` itself, or the single ``*.mcap`` in a directory.

    Raises
    ------
    BagRecoveryError
        When there is no such file, or a directory holds several.
    """
    path = Path(source)
    if path.is_dir():
        files = sorted(path.glob("*.mcap"))
        if len(files) != 1:
            raise BagRecoveryError(
                f"{path} holds {len(files)} .mcap files; give the file to recover itself")
        return files[0]
    if not path.is_file():
        raise BagRecoveryError(f"{path} does not exist; give a bag directory or an .mcap file")
    return path


def default_destination(source: str | os.PathLike[str]) -> Path:
    """``<bag directory>_recovered`` next to a bag directory; ``<stem>_recovered`` next to
    a lone .mcap file."""
    path = Path(source)
    if path.is_file():
        return path.parent / f"{path.stem}_recovered"
    return path.parent / f"{path.name}_recovered"


def recover_bag(source: str | os.PathLike[str],
                destination: str | os.PathLike[str]) -> RecoveryReport:
    """Copy every intact record of a (possibly damaged) bag into a new, valid bag.

    Parameters
    ----------
    source : str or os.PathLike
        A bag directory (its one ``.mcap``) or an ``.mcap`` file.
    destination : str or os.PathLike
        The bag directory to create; it must not exist.

    Returns
    -------
    RecoveryReport
        What was kept and lost.

    Raises
    ------
    BagRecoveryError
        When the source cannot be found, is not an MCAP file, or the destination exists.
    """
    mcap_path = find_mcap(source)
    destination = Path(destination)
    if destination.exists():
        raise BagRecoveryError(f"{destination} already exists; choose another destination")
    file_size = mcap_path.stat().st_size
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    added: set[int] = set()
    metadata: list[Metadata] = []
    damage: McapDamageError | None = None
    end: ScanEnd | None = None
    with open(mcap_path, "rb") as stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise BagRecoveryError(f"{mcap_path} is not an MCAP file (no MCAP magic at its "
                                   "start); nothing to recover")
    writer = SessionBagWriter(destination)
    writer.start()
    try:
        records = scan_records(mcap_path)
        while True:
            try:
                item = next(records)
            except StopIteration as stop:
                end = stop.value
                break
            except McapDamageError as err:
                damage = err
                break
            _copy(item.record, writer, schemas, channels, added, metadata)
        if damage is not None:
            kept_bytes = damage.offset
        else:  # a finished file's summary is rebuilt, not lost
            kept_bytes = file_size if end.finished else end.offset
        stats = summary_statistics(mcap_path) if damage is not None else None
        counts = writer.message_counts
        report = RecoveryReport(
            source=mcap_path, destination=destination, file_size=file_size,
            kept_bytes=kept_bytes, message_counts=counts,
            finished=end.finished if end is not None else False,
            damage_offset=damage.offset if damage is not None else None,
            damage_reason=damage.reason if damage is not None else "",
            lost_messages=(max(int(stats.message_count) - sum(counts.values()), 0)
                           if stats is not None else (0 if damage is None else None)),
            lost_span_ns=damage.chunk_span_ns if damage is not None else None)
        for item in metadata:
            writer.add_metadata(item.name, item.metadata)
        writer.add_metadata(RECOVERY_METADATA_RECORD, {
            "source": str(mcap_path), "file_size": str(file_size),
            "kept_bytes": str(kept_bytes),
            "damage_offset": "" if damage is None else str(damage.offset),
            "damage_reason": report.damage_reason,
            "lost_messages": "" if report.lost_messages is None else str(report.lost_messages),
        })
    finally:
        writer.finish()
    return report


def _copy(record: object, writer: SessionBagWriter, schemas: dict[int, Schema],
          channels: dict[int, Channel], added: set[int], metadata: list[Metadata]) -> None:
    """Hand one scanned record to the writer (channels are added at their first message)."""
    if isinstance(record, Schema):
        schemas[record.id] = record
    elif isinstance(record, Channel):
        channels[record.id] = record
    elif isinstance(record, Message):
        channel = channels.get(record.channel_id)
        if channel is None:
            return  # a message of a channel never defined: cannot be decoded, left out
        if record.channel_id not in added:
            _add_channel(channel, schemas.get(channel.schema_id), writer)
            added.add(record.channel_id)
        writer.write(channel.topic, record.data, log_time_ns=record.log_time,
                     publish_time_ns=record.publish_time, sequence=record.sequence)
    elif isinstance(record, Metadata) and record.name != ROSBAG2_METADATA_RECORD:
        if record.name != RECOVERY_METADATA_RECORD:
            metadata.append(record)
    elif isinstance(record, Attachment):
        pass  # fingerps bags carry none


def _add_channel(channel: Channel, schema: Schema | None, writer: SessionBagWriter) -> None:
    if schema is None:
        raise BagRecoveryError(
            f"channel {channel.topic} refers to schema {channel.schema_id}, which is not in "
            "the file; this is not a ROS 2 bag fingerps can recover")
    definition = MessageDefinition(schema.name, schema.encoding,
                                   schema.data.decode("utf-8", errors="replace"))
    try:
        writer.add_topic(
            channel.topic, schema.name,
            offered_qos_yaml=channel.metadata.get("offered_qos_profiles", "[]"),
            serialization_format=channel.message_encoding,
            type_hash=channel.metadata.get("topic_type_hash", ""),
            definition=definition)
    except SessionBagError as err:
        raise BagRecoveryError(f"cannot copy channel {channel.topic}: {err}") from None
