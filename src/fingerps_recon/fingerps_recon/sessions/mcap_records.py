"""Walking an MCAP file record by record, with byte offsets, past any damage.

The ``mcap`` library's readers either need the summary at the end of the file (which a
killed recorder never writes) or stop at the first bad record. `McapScan` frames each
top-level record itself (opcode + length, checked against the file size), parses it with the
library's record classes (the record must fill exactly its length), opens chunks with
`breakup_chunk` (CRC checked, decompressed size checked) and yields the records with the
offset they start at.

At a record that is cut short, has an unknown opcode, a wrong length, or does not parse or
decompress, it does not stop: it resynchronises on the next plausible record (a Chunk whose
decompression and CRC succeed, a DataEnd, or a chain of well-framed records leading to one
or to the exact end of the file), records the skipped bytes as a `DamagedRange`, and carries
on. Every intact chunk is read. Channels and schemas defined in a damaged chunk are taken
from the file's summary (the writer repeats them there) when the summary, or the copy after
the DataEnd record, is readable; messages whose channel cannot be defined anywhere are
counted in `McapScan.orphans`, never silently dropped. Message Index records that follow a
damaged chunk say how many messages of each channel it held (`DamagedRange.lost_by_channel`).

A file that simply ends at a record boundary without its footer (what a SIGKILL leaves) is
not damage: `McapScan.finished` is False and `McapScan.damage` is empty.

No rclpy here.
"""

from __future__ import annotations

import io
import mmap
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import breakup_chunk
from zstandard import ZstdError

from fingerps_recon.errors import McapDamageError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_HEADER_SIZE = _RECORD_HEADER.size
_FOOTER_SIZE = _HEADER_SIZE + 8 + 8 + 4
_DATA_END_HEAD = _RECORD_HEADER.pack(Opcode.DATA_END, 4)
_KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
_RESYNC_OPCODES = (Opcode.CHUNK, Opcode.MESSAGE_INDEX, Opcode.METADATA, Opcode.ATTACHMENT,
                   Opcode.DATA_END)
"""Records a resynchronisation may land on (what a chunked writer puts in the data section)."""
_CHAIN_LIMIT = 64
_MAX_UNCOMPRESSED = 4 * 2**30
_PARSE_ERRORS = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError,
                 KeyError, IndexError, OverflowError, MemoryError, ZstdError,
                 RuntimeError)  # lz4.frame raises RuntimeError on bad data
_READERS = {
    Opcode.HEADER: None, Opcode.FOOTER: Footer.read, Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read, Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read, Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.METADATA: Metadata.read, Opcode.ATTACHMENT: Attachment.read,
    Opcode.DATA_END: DataEnd.read, Opcode.STATISTICS: Statistics.read,
}


@dataclass(frozen=True)
class DamagedRange:
    """Bytes of the data section that could not be read, and what they held when knowable.

    Attributes
    ----------
    start, end : int
        Byte range skipped, ``[start, end)``; ``end`` is where reading resumed (or the file
        size).
    reason : str
        What was wrong at ``start``.
    opcode : int
        The opcode byte found at ``start`` (``0x06`` for a chunk, anything else when it was
        corrupted).
    lost_by_channel : dict[int, int]
        Messages per channel id of the damaged chunk(s), from the Message Index records
        after them; empty when those were lost too.
    span_ns : tuple[int, int] or None
        Log-time range of the damaged chunk, when its header could be read.
    """

    start: int
    end: int
    reason: str
    opcode: int = -1
    lost_by_channel: dict[int, int] = field(default_factory=dict)
    span_ns: tuple[int, int] | None = None

    @property
    def size(self) -> int:
        """Bytes skipped."""
        return self.end - self.start

    def describe(self) -> str:
        """``bytes 1234..5678 (4444 bytes): <reason>``."""
        return f"bytes {self.start}..{self.end} ({self.size} bytes): {self.reason}"


@dataclass(frozen=True)
class McapSummary:
    """What the summary section (or any readable part of it) repeats about the file."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    statistics: Statistics | None = None
    chunk_indexes: tuple[ChunkIndex, ...] = ()
    source: str = ""
    """``"footer"`` (found through the footer), ``"after DataEnd"`` (found by searching for
    the DataEnd record) or ``""`` (none)."""


@dataclass(frozen=True)
class ScannedRecord:
    """One record of the data section: where its top-level record starts, and the record.

    Records inside a chunk carry the offset of their chunk; schemas and channels taken from
    the summary (their chunk was damaged) carry ``from_summary=True``.
    """

    offset: int
    record: McapRecord
    in_chunk: bool = False
    from_summary: bool = False


@dataclass(frozen=True)
class ScanEnd:
    """How the data section ended (the value `scan_records` returns)."""

    offset: int
    """Byte offset just after the last intact record."""
    finished: bool
    """True when the data section ended with a DataEnd record (a finished file)."""


class _ReadError(Exception):
    """A record that cannot be read at an offset (internal)."""


def _frame(buf: mmap.mmap | bytes, offset: int, size: int) -> tuple[int, int]:
    """(opcode, end) of the record at ``offset``; `_ReadError` when it cannot be framed."""
    if offset + _HEADER_SIZE > size:
        raise _ReadError(f"record header cut short ({size - offset} of {_HEADER_SIZE} bytes)")
    opcode, length = _RECORD_HEADER.unpack_from(buf, offset)
    if opcode not in _KNOWN_OPCODES:
        raise _ReadError(f"unknown record opcode 0x{opcode:02x} (a corrupt opcode: fingerps bags "
                   "hold only standard MCAP records)")
    end = offset + _HEADER_SIZE + length
    if end > size:
        raise _ReadError(f"{Opcode(opcode).name} record of {length} bytes runs {end - size} bytes "
                   "past the end of the file (the file was cut short, or the length is "
                   "corrupt)")
    return opcode, end


def _parse(buf: mmap.mmap | bytes, offset: int,
           size: int) -> tuple[int, int, McapRecord | None, list[McapRecord] | None]:
    """(opcode, end, record, chunk contents) of the record at ``offset``; `_ReadError` when the
    record is cut, unknown, not exactly its length, or (a chunk) fails decompression/CRC."""
    opcode, end = _frame(buf, offset, size)
    body_start = offset + _HEADER_SIZE
    reader = _READERS.get(Opcode(opcode))
    if reader is None:  # a Header, SummaryOffset, ... : framed, not needed
        if opcode == Opcode.HEADER and offset != len(MAGIC):
            raise _ReadError("HEADER record in the middle of the file")
        return opcode, end, None, None
    stream = ReadDataStream(io.BytesIO(buf[body_start:end]))
    name = Opcode(opcode).name
    try:
        record = reader(stream)
        if stream.count != end - body_start:
            raise _ReadError(f"{name} record fills {stream.count} of its {end - body_start} bytes "
                       "(a corrupt length)")
        inner = None
        if isinstance(record, Chunk):
            if record.uncompressed_size > _MAX_UNCOMPRESSED:
                raise _ReadError(f"CHUNK claims {record.uncompressed_size} uncompressed bytes")
            inner = breakup_chunk(record, validate_crc=True)
    except _PARSE_ERRORS as err:
        raise _ReadError(f"{name} record does not parse ({type(err).__name__}: {err})") from None
    return opcode, end, record, inner


def _chunk_span(buf: mmap.mmap | bytes, offset: int, size: int) -> tuple[int, int] | None:
    """Log-time range from the first bytes of a (possibly damaged) chunk record's body."""
    if offset + _HEADER_SIZE + 16 > size or buf[offset] != Opcode.CHUNK:
        return None
    start, end = struct.unpack_from("<QQ", buf, offset + _HEADER_SIZE)
    return (start, end) if start <= end else None


class McapScan:
    """The data-section records of an MCAP file in file order, chunks opened, damage skipped.

    Iterate it (once) for `ScannedRecord` items (Schema, Channel, Message, Metadata,
    Attachment; Chunk records are replaced by their contents, index records are left out);
    afterwards `damage`, `orphans`, `finished` and `end_offset` say how it went.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file.

    Raises
    ------
    McapDamageError
        At construction, when the file does not start with the MCAP magic.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.file_size = self.path.stat().st_size
        with open(self.path, "rb") as stream:
            if stream.read(len(MAGIC)) != MAGIC:
                raise McapDamageError(self.path, 0, "no MCAP magic at the start: not an MCAP "
                                      "file", self.file_size)
        self.damage: list[DamagedRange] = []
        """Damaged ranges, in file order."""
        self.orphans: dict[int, int] = {}
        """Messages per channel id that were read intact but whose channel (or its schema)
        is defined nowhere readable: they cannot be decoded and are not yielded."""
        self.orphan_topics: dict[int, str] = {}
        """Topics of orphaned channels whose Channel record was read (schema missing)."""
        self.finished = False
        """Whether the data section ended with its DataEnd record."""
        self.end_offset = len(MAGIC)
        """Byte offset after the last record read."""
        self.chunks_read = 0
        """Intact chunks read."""
        self._summary: McapSummary | None = None
        self._buf: mmap.mmap | None = None

    # ---- summary -----------------------------------------------------------------------------

    @property
    def summary(self) -> McapSummary:
        """The summary section's schemas, channels, statistics and chunk indexes (read on first
        use; an empty `McapSummary` when there is none)."""
        if self._summary is None:
            if self._buf is not None:
                self._summary = _read_summary(self._buf, self.file_size)
            else:
                with open(self.path, "rb") as stream, \
                        mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                    self._summary = _read_summary(buf, self.file_size)
        return self._summary

    # ---- scanning ----------------------------------------------------------------------------

    def __iter__(self) -> Iterator[ScannedRecord]:
        self.damage, self.orphans, self.orphan_topics = [], {}, {}
        self.finished, self.end_offset, self.chunks_read = False, len(MAGIC), 0
        with open(self.path, "rb") as stream, \
                mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            self._buf = buf
            try:
                yield from self._scan(buf)
            finally:
                self._buf = None

    def _scan(self, buf: mmap.mmap) -> Iterator[ScannedRecord]:
        size = self.file_size
        schemas: set[int] = set()
        channels: dict[int, Channel | None] = {}  # None: defined nowhere readable
        offset = len(MAGIC)
        indexes_lost = False  # Message Index records now belong to a damaged chunk
        while offset < size:
            try:
                _, end, record, inner = _parse(buf, offset, size)
            except _ReadError as bad:
                resume = self._resync(buf, offset + 1, size)
                previous_ok = not indexes_lost
                self.damage.append(DamagedRange(
                    start=offset, end=size if resume is None else resume, reason=str(bad),
                    opcode=buf[offset], span_ns=_chunk_span(buf, offset, size)))
                # A damaged index after an intact chunk: the indexes after it are the chunk's.
                indexes_lost = not (previous_ok and buf[offset] == Opcode.MESSAGE_INDEX)
                if resume is None:
                    offset = size
                    break
                offset = resume
                continue
            self.end_offset = end
            if isinstance(record, (DataEnd, Footer)):
                self.finished = True
                return
            if isinstance(record, MessageIndex):
                if indexes_lost and self.damage and record.records:
                    lost = dict(self.damage[-1].lost_by_channel)
                    lost[record.channel_id] = lost.get(record.channel_id, 0) + len(record.records)
                    self.damage[-1] = replace(self.damage[-1], lost_by_channel=lost)
            elif inner is not None:
                self.chunks_read += 1
                indexes_lost = False
                for item in inner:
                    yield from self._definitions_then(item, offset, True, schemas, channels)
            elif isinstance(record, (Schema, Channel, Message, Metadata, Attachment)):
                yield from self._definitions_then(record, offset, False, schemas, channels)
            offset = end
        self.end_offset = offset

    def _definitions_then(self, record: McapRecord, offset: int, in_chunk: bool,
                          schemas: set[int], channels: dict[int, Channel | None],
                          from_summary: bool = False) -> Iterator[ScannedRecord]:
        """Yield ``record``, preceded by the summary's copy of any definition it needs that
        was lost with a damaged chunk; count messages nothing defines as orphans."""
        if isinstance(record, Schema):
            if record.id not in schemas:
                schemas.add(record.id)
                yield ScannedRecord(offset, record, in_chunk, from_summary)
            return
        if isinstance(record, Channel):
            if record.id in channels and channels[record.id] is not None:
                return
            if record.schema_id != 0 and record.schema_id not in schemas:
                schema = self.summary.schemas.get(record.schema_id)
                if schema is None:
                    channels[record.id] = None
                    self.orphan_topics[record.id] = record.topic
                    return
                schemas.add(schema.id)
                yield ScannedRecord(offset, schema, in_chunk, from_summary=True)
            channels[record.id] = record
            yield ScannedRecord(offset, record, in_chunk, from_summary)
            return
        if isinstance(record, Message) and channels.get(record.channel_id) is None:
            channel = None if record.channel_id in channels else \
                self.summary.channels.get(record.channel_id)
            if channel is not None:
                yield from self._definitions_then(channel, offset, in_chunk, schemas, channels,
                                                  from_summary=True)
                channel = channels.get(record.channel_id)
            if channel is None:
                channels.setdefault(record.channel_id, None)
                self.orphans[record.channel_id] = self.orphans.get(record.channel_id, 0) + 1
                return
        yield ScannedRecord(offset, record, in_chunk)

    def _resync(self, buf: mmap.mmap, start: int, size: int) -> int | None:
        """Offset of the next plausible record at or after ``start``; None when there is none.

        Plausible: a Chunk that decompresses with a matching CRC, a DataEnd, or another
        data-section record that parses and starts a chain of well-framed records ending in
        one of those or exactly at the end of the file.
        """
        found = {op: buf.find(bytes([op]), start) for op in _RESYNC_OPCODES}
        while True:
            live = [p for p in found.values() if p >= 0]
            if not live:
                return None
            position = min(live)
            if self._plausible(buf, position, size):
                return position
            for op, p in found.items():
                if p == position:
                    found[op] = buf.find(bytes([op]), position + 1)

    @staticmethod
    def _plausible(buf: mmap.mmap, position: int, size: int) -> bool:
        try:
            _frame(buf, position, size)
        except _ReadError:
            return False
        for _ in range(_CHAIN_LIMIT):
            if position == size:
                return True
            try:
                opcode, end, _record, _inner = _parse(buf, position, size)
            except _ReadError:
                return False
            if opcode in (Opcode.CHUNK, Opcode.DATA_END):
                return True
            if opcode not in _RESYNC_OPCODES:
                return False
            position = end
        return True


def _read_summary(buf: mmap.mmap | bytes, size: int) -> McapSummary:
    """Everything readable of the summary: through the footer, else after the last DataEnd."""
    footer_at = size - len(MAGIC) - _FOOTER_SIZE
    start, stop, source = -1, -1, ""
    if footer_at > len(MAGIC) and buf[size - len(MAGIC):size] == MAGIC:
        try:
            _, _, footer, _ = _parse(buf, footer_at, size - len(MAGIC))
        except _ReadError:
            footer = None
        if isinstance(footer, Footer) and len(MAGIC) < footer.summary_start < footer_at:
            start, stop, source = footer.summary_start, footer_at, "footer"
    if start < 0:
        data_end = buf.rfind(_DATA_END_HEAD)
        if data_end < 0:
            return McapSummary()
        start, stop, source = data_end + _HEADER_SIZE + 4, size, "after DataEnd"
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    statistics: Statistics | None = None
    chunk_indexes: list[ChunkIndex] = []
    offset = start
    while offset < stop:
        try:
            _, end, record, _ = _parse(buf, offset, stop)
        except _ReadError:
            break  # keep what was read before the damage
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Statistics):
            statistics = record
        elif isinstance(record, ChunkIndex):
            chunk_indexes.append(record)
        elif isinstance(record, Footer):
            break
        offset = end
    return McapSummary(schemas=schemas, channels=channels, statistics=statistics,
                       chunk_indexes=tuple(chunk_indexes), source=source)


def scan_records(path: str | os.PathLike[str]) -> Iterator[ScannedRecord]:
    """Yield every intact data-section record of an MCAP file; raise at the end if damaged.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file.

    Yields
    ------
    ScannedRecord
        As `McapScan` yields them (damaged chunks skipped, reading resumed after them).

    Returns
    -------
    ScanEnd
        As the generator's return value (``StopIteration.value``).

    Raises
    ------
    McapDamageError
        After every intact record was yielded, when the file had damage (naming the first
        damaged offset and listing the others), or at once for a file that is no MCAP.
    """
    scan = McapScan(path)
    yield from scan
    if scan.damage or scan.orphans:
        raise damage_error(scan)
    return ScanEnd(offset=scan.end_offset, finished=scan.finished)


def damage_error(scan: McapScan) -> McapDamageError:
    """The `McapDamageError` describing a finished scan's damage and orphaned messages."""
    orphaned = ""
    if scan.orphans:
        names = ", ".join(scan.orphan_topics.get(c, f"channel {c}") for c in sorted(scan.orphans))
        orphaned = (f"; {sum(scan.orphans.values())} intact messages of {names} cannot be "
                    "decoded: their channel definition was lost with a damaged chunk and "
                    "the file has no readable summary")
    if not scan.damage:
        return McapDamageError(scan.path, scan.end_offset, orphaned[2:], scan.file_size)
    first = scan.damage[0]
    return McapDamageError(scan.path, first.start, first.reason + orphaned, scan.file_size,
                           damage=tuple(scan.damage))


def summary_statistics(path: str | os.PathLike[str]) -> Statistics | None:
    """The Statistics record of the file's summary, or None (no readable summary)."""
    try:
        return McapScan(path).summary.statistics
    except McapDamageError:
        return None


__all__ = ["DamagedRange", "McapScan", "McapSummary", "ScanEnd", "ScannedRecord",
           "damage_error", "scan_records", "summary_statistics"]
