"""Recovering an unfinished or damaged session bag into a valid one.

A recorder killed with SIGKILL (or stopped by a full disk) leaves an MCAP file without its
summary and a bag directory without metadata.yaml; a file cut by a copy or a disk error may
end in the middle of a chunk; a flipped bit may damage any chunk. `recover_bag` reads such a
file with `fingerps_recon.sessions.mcap_records.McapScan`, which skips each damaged chunk and
resynchronises on the next intact one, keeps every schema, channel, message and metadata
record of every intact chunk (channels and schemas defined in a damaged chunk are taken from
the file's summary when it is readable), writes them with `SessionBagWriter` into a new bag
directory (MCAP with summary + metadata.yaml), and says in a `RecoveryReport` what was kept
and what was lost: the damaged byte ranges and why, the chunks lost, and the messages lost
per topic (exact when the source's summary survived, else at least the count its message
indexes give).

Each channel keeps its original schema text, QoS metadata and type hash; the messages keep
their log and publish times and sequence numbers. The new bag gets one more metadata record,
``fingerps.recovery``, with the report.

No rclpy here.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.records import Attachment, Channel, Message, Metadata, Schema

from fingerps_recon.errors import BagRecoveryError, SessionBagError
from fingerps_recon.sessions.bag_metadata import METADATA_FILENAME
from fingerps_recon.sessions.mcap_records import DamagedRange, McapScan, McapSummary
from fingerps_recon.sessions.message_definition import MessageDefinition
from fingerps_recon.sessions.session_bag import ROSBAG2_METADATA_RECORD, SessionBagWriter

RECOVERY_METADATA_RECORD = "fingerps.recovery"


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
    message_counts : dict[str, int]
        Messages kept per topic.
    finished : bool
        Whether the source had its end-of-data record (it was finished, not killed).
    damage : tuple[DamagedRange, ...]
        The damaged byte ranges of the data section, in file order (empty: no damage).
    lost_counts : dict[str, int]
        Messages lost per topic (a channel whose Channel record was lost too is named
        ``channel <id>``).
    lost_exact : bool
        True when `lost_counts` comes from the source's summary statistics (exact); False
        when it comes from the message indexes after damaged chunks (a lower bound).
    chunks_kept : int
        Intact chunks read.
    chunks_lost : int
        Chunks in the damaged ranges (from the summary's chunk indexes when readable, else
        those whose start could still be recognised: a lower bound).
    summary_source : str
        Where the source's summary was found (``"footer"``, ``"after DataEnd"``, ``""``).
    definitions_from_summary : tuple[str, ...]
        Topics whose channel (or schema) was lost with a damaged chunk and was taken from
        the summary.
    lost_spans_ns : tuple[tuple[int, int], ...]
        Log-time ranges of the lost chunks, when known.
    undecodable : dict[str, int]
        Of the lost messages: those read intact whose channel definition was lost with a
        damaged chunk and is not in a readable summary, per channel.
    """

    source: Path
    destination: Path
    file_size: int
    message_counts: dict[str, int] = field(default_factory=dict)
    finished: bool = False
    damage: tuple[DamagedRange, ...] = ()
    lost_counts: dict[str, int] = field(default_factory=dict)
    lost_exact: bool = True
    chunks_kept: int = 0
    chunks_lost: int = 0
    summary_source: str = ""
    definitions_from_summary: tuple[str, ...] = ()
    lost_spans_ns: tuple[tuple[int, int], ...] = ()
    undecodable: dict[str, int] = field(default_factory=dict)

    @property
    def message_count(self) -> int:
        """Messages kept."""
        return sum(self.message_counts.values())

    @property
    def lost_messages(self) -> int:
        """Messages lost (exact or a lower bound: see `lost_exact`)."""
        return sum(self.lost_counts.values())

    @property
    def lost_bytes(self) -> int:
        """Bytes of the source in damaged ranges."""
        return sum(d.size for d in self.damage)

    @property
    def kept_bytes(self) -> int:
        """Bytes of the source outside the damaged ranges."""
        return self.file_size - self.lost_bytes

    @property
    def damage_offset(self) -> int | None:
        """Byte offset of the first damage; None without damage."""
        return self.damage[0].start if self.damage else None

    @property
    def damage_reason(self) -> str:
        """What was wrong at the first damage (``""`` without damage)."""
        return self.damage[0].reason if self.damage else ""

    def describe(self) -> str:
        """A few lines for people: what was kept, where the damage is, what was lost."""
        lines = [f"recovered {self.source} -> {self.destination}"]
        counts = ", ".join(f"{t}: {n}" for t, n in self.message_counts.items()) or "none"
        lines.append(f"  kept   : {self.message_count} messages ({counts}) from "
                     f"{self.chunks_kept} intact chunks; {self.kept_bytes} of "
                     f"{self.file_size} bytes")
        if self.damage:
            bound = "" if self.lost_exact else "at least "
            lines.append(f"  damage : {len(self.damage)} damaged range(s), {bound}"
                         f"{self.chunks_lost} chunk(s) lost:")
            for item in self.damage:
                lines.append(f"           at byte offset {item.start} (to {item.end}, "
                             f"{item.size} bytes): {item.reason}")
        elif self.finished:
            lines.append("  damage : none (the file was finished; its summary was rebuilt)")
        else:
            lines.append(f"  damage : none; the file ends at byte offset {self.file_size} "
                         "without its summary (the writer was killed between chunks; what it "
                         "had not yet written - at most one chunk or flush_period - never "
                         "reached the file)")
        if self.lost_messages or self.damage:
            per_topic = ", ".join(f"{t}: {n}" for t, n in self.lost_counts.items())
            how = ("exact, from the source's summary" if self.lost_exact else
                   "at least; the source has no readable summary, so messages of damaged "
                   "chunks whose message indexes were lost too are not counted")
            lost = f"{self.lost_messages} messages ({per_topic or 'none'}; {how})"
        else:
            lost = "no messages"
        spans = ""
        if self.lost_spans_ns:
            spans = ", logged " + ", ".join(f"{a / 1e9:.3f} .. {b / 1e9:.3f} s"
                                            for a, b in self.lost_spans_ns[:5]) + " (epoch)"
        lines.append(f"  lost   : {lost}, {self.lost_bytes} bytes{spans}")
        if self.undecodable:
            lines.append("  note   : " + ", ".join(
                f"{n} intact messages of {c}" for c, n in self.undecodable.items()) +
                " could not be kept: their channel definition was lost with a damaged chunk "
                "and the source has no readable summary")
        if self.definitions_from_summary:
            lines.append("  note   : channel definitions of " + ", ".join(
                self.definitions_from_summary) + " were lost with a damaged chunk and taken "
                "from the source's summary")
        return "\n".join(lines)


def bag_pieces(source: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a bag, in order.

    ``source`` itself when it is a file. In a bag directory: the files its metadata.yaml
    lists (``relative_file_paths``) when it has one, else every ``*.mcap`` in the order of
    the ``_<n>`` index rosbag2 gives split pieces (a killed recorder writes no metadata.yaml).

    Raises
    ------
    BagRecoveryError
        When there is no such path, no ``.mcap`` file, or a piece metadata.yaml lists is
        missing.
    """
    path = Path(source)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise BagRecoveryError(f"{path} does not exist; give a bag directory or an .mcap file")
    listed = _listed_pieces(path / METADATA_FILENAME)
    if listed:
        missing = [name for name in listed if not (path / name).is_file()]
        if missing:
            raise BagRecoveryError(
                f"{path}: metadata.yaml lists {', '.join(missing)}, which "
                f"{'is' if len(missing) == 1 else 'are'} missing (deleted or moved); read or "
                "recover the pieces that are there by giving each .mcap file")
        return [path / name for name in listed]
    files = sorted(path.glob("*.mcap"), key=_piece_order)
    if not files:
        raise BagRecoveryError(f"{path} holds no .mcap file; give a bag directory or an .mcap "
                               "file")
    return files


def _listed_pieces(metadata_path: Path) -> list[str]:
    """``relative_file_paths`` of a readable metadata.yaml ([] when absent or unreadable:
    the directory is then read by its file names)."""
    try:
        document = yaml.safe_load(metadata_path.read_text(encoding="utf-8"))
        names = document["rosbag2_bagfile_information"]["relative_file_paths"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return []
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        return []
    return [Path(name).name for name in names]


def _piece_order(path: Path) -> tuple[int, str]:
    match = re.search(r"_(\d+)$", path.stem)
    return (int(match.group(1)) if match else 1 << 62, path.name)


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

    A bag split into pieces (``DIR_0.mcap``, ``DIR_1.mcap``, ...) is recovered piece by piece
    into one MCAP file; the report adds the pieces up (damage reasons name their piece).

    Parameters
    ----------
    source : str or os.PathLike
        A bag directory (every piece: `bag_pieces`) or an ``.mcap`` file.
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
    pieces = bag_pieces(source)
    destination = Path(destination)
    if destination.exists():
        raise BagRecoveryError(f"{destination} already exists; choose another destination")
    for mcap_path in pieces:
        with open(mcap_path, "rb") as stream:
            if stream.read(8) != b"\x89MCAP0\r\n":
                raise BagRecoveryError(f"{mcap_path} is not an MCAP file (no MCAP magic at its "
                                       "start); nothing to recover")
    writer = SessionBagWriter(destination)
    writer.start()
    try:
        reports: list[RecoveryReport] = []
        metadata: dict[tuple[str, str], Metadata] = {}  # each piece repeats the records
        for mcap_path in pieces:
            scan = McapScan(mcap_path)
            copier = _Copier()
            for item in scan:
                copier.copy(item.record, writer, from_summary=item.from_summary)
            summary = scan.summary if (scan.damage or scan.orphans or copier.undecodable) \
                else McapSummary()
            reports.append(_report(scan, summary, copier, mcap_path, destination,
                                   mcap_path.stat().st_size, {}))
            for item in copier.metadata:
                metadata.setdefault((item.name, json.dumps(item.metadata, sort_keys=True)), item)
        report = _combined(reports, Path(source) if len(pieces) > 1 else pieces[0],
                           writer.message_counts)
        for item in metadata.values():
            writer.add_metadata(item.name, item.metadata)
        writer.add_metadata(RECOVERY_METADATA_RECORD, {
            "source": str(report.source), "file_size": str(report.file_size),
            "kept_bytes": str(report.kept_bytes),
            "damage_offset": "" if report.damage_offset is None else str(report.damage_offset),
            "damage_reason": report.damage_reason,
            "damaged_ranges": json.dumps([[d.start, d.end, d.reason] for d in report.damage]),
            "chunks_lost": str(report.chunks_lost),
            "lost_messages": str(report.lost_messages),
            "lost_messages_exact": "true" if report.lost_exact else "false",
            "lost_by_topic": json.dumps(report.lost_counts),
        })
    finally:
        writer.finish()
    return report


def _combined(reports: list[RecoveryReport], source: Path,
              counts: dict[str, int]) -> RecoveryReport:
    """One report for the pieces of a bag (the single piece's own when there is one)."""
    if len(reports) == 1:
        return dataclasses.replace(reports[0], message_counts=counts)

    def added(field_name: str) -> dict[str, int]:
        total: dict[str, int] = {}
        for report in reports:
            for key, n in getattr(report, field_name).items():
                total[key] = total.get(key, 0) + n
        return total

    return RecoveryReport(
        source=source, destination=reports[0].destination,
        file_size=sum(r.file_size for r in reports), message_counts=counts,
        finished=all(r.finished for r in reports),
        damage=tuple(dataclasses.replace(d, reason=f"{r.source.name}: {d.reason}")
                     for r in reports for d in r.damage),
        lost_counts=added("lost_counts"), lost_exact=all(r.lost_exact for r in reports),
        chunks_kept=sum(r.chunks_kept for r in reports),
        chunks_lost=sum(r.chunks_lost for r in reports),
        summary_source=reports[-1].summary_source,
        definitions_from_summary=tuple(t for r in reports for t in r.definitions_from_summary),
        lost_spans_ns=tuple(s for r in reports for s in r.lost_spans_ns),
        undecodable=added("undecodable"))


def _report(scan: McapScan, summary: McapSummary, copier: _Copier, mcap_path: Path,
            destination: Path, file_size: int, counts: dict[str, int]) -> RecoveryReport:
    """Work out what was lost from the scan, the source's summary and what was copied."""
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    topics.update(scan.orphan_topics)
    topics.update(copier.topics)

    def name(channel_id: int) -> str:
        return topics.get(channel_id, f"channel {channel_id}")

    lost: dict[str, int] = {}
    stats = summary.statistics
    exact = stats is not None or not (scan.damage or scan.orphans or copier.undecodable)
    if stats is not None:
        for channel_id, total in sorted(stats.channel_message_counts.items()):
            missing = total - copier.kept.get(channel_id, 0)
            if missing > 0:
                lost[name(channel_id)] = lost.get(name(channel_id), 0) + missing
    else:
        sources = [d.lost_by_channel for d in scan.damage] + [scan.orphans, copier.undecodable]
        for per_channel in sources:
            for channel_id, n in per_channel.items():
                lost[name(channel_id)] = lost.get(name(channel_id), 0) + n
    undecodable: dict[str, int] = {}
    for per_channel in (scan.orphans, copier.undecodable):
        for channel_id, n in per_channel.items():
            undecodable[name(channel_id)] = undecodable.get(name(channel_id), 0) + n
    in_damage = [c for c in summary.chunk_indexes
                 if any(d.start <= c.chunk_start_offset < d.end for d in scan.damage)]
    if summary.chunk_indexes:
        chunks_lost = len(in_damage)
        spans = tuple((c.message_start_time, c.message_end_time) for c in in_damage)
    else:
        chunks_lost = sum(1 for d in scan.damage
                          if d.opcode == 0x06 or d.lost_by_channel)  # 0x06: Chunk
        spans = tuple(d.span_ns for d in scan.damage if d.span_ns is not None)
    return RecoveryReport(
        source=mcap_path, destination=destination, file_size=file_size,
        message_counts=counts, finished=scan.finished, damage=tuple(scan.damage),
        lost_counts=lost, lost_exact=exact, chunks_kept=scan.chunks_read,
        chunks_lost=chunks_lost, summary_source=summary.source,
        definitions_from_summary=tuple(copier.from_summary), lost_spans_ns=spans,
        undecodable=undecodable)


class _Copier:
    """Hands scanned records to the writer (channels are added at their first message) and
    counts what it kept per channel id."""

    def __init__(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.added: set[int] = set()
        self.metadata: list[Metadata] = []
        self.kept: dict[int, int] = {}
        self.undecodable: dict[int, int] = {}
        self.topics: dict[int, str] = {}
        self.from_summary: list[str] = []

    def copy(self, record: object, writer: SessionBagWriter, *, from_summary: bool) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
            self.topics[record.id] = record.topic
            if from_summary:
                self.from_summary.append(record.topic)
        elif isinstance(record, Message):
            channel = self.channels.get(record.channel_id)
            if channel is None:  # McapScan yields no such message; counted all the same
                self.undecodable[record.channel_id] = \
                    self.undecodable.get(record.channel_id, 0) + 1
                return
            if record.channel_id not in self.added:
                schema = self.schemas.get(channel.schema_id)
                if schema is None:
                    self.undecodable[record.channel_id] = \
                        self.undecodable.get(record.channel_id, 0) + 1
                    return
                if not writer.has_topic(channel.topic):  # a later piece repeats channels
                    _add_channel(channel, schema, writer)
                self.added.add(record.channel_id)
            writer.write(channel.topic, record.data, log_time_ns=record.log_time,
                         publish_time_ns=record.publish_time, sequence=record.sequence)
            self.kept[record.channel_id] = self.kept.get(record.channel_id, 0) + 1
        elif isinstance(record, Metadata) and record.name not in (
                ROSBAG2_METADATA_RECORD, RECOVERY_METADATA_RECORD):
            self.metadata.append(record)
        elif isinstance(record, Attachment):
            pass  # fingerps bags carry none


def _add_channel(channel: Channel, schema: Schema, writer: SessionBagWriter) -> None:
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
