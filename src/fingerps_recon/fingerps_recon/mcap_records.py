"""Walking an MCAP file record by record, with byte offsets, up to the first damage.

The ``mcap`` library's readers either need the summary at the end of the file (which a
killed recorder never writes) or read on blindly past a short record. `scan_records` frames
each top-level record itself (opcode + length, checked against the file size), parses it
with the library's `StreamReader`, opens chunks with `breakup_chunk` (CRC checked), and
yields the records with the offset they start at. At the first record that is cut short or
does not parse it raises `McapDamageError` naming that offset; everything yielded before it
is intact. A file that simply ends at a record boundary without its footer (what a SIGKILL
leaves) is not damage: `ScanEnd.finished` is False.

No rclpy here.
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    DataEnd,
    Footer,
    McapRecord,
    Message,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from zstandard import ZstdError

from fingerps_recon.errors import FingerpsReconError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_FOOTER_SIZE = _RECORD_HEADER.size + 8 + 8 + 4
_KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
_PARSE_ERRORS = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError,
                 KeyError, IndexError, OverflowError, MemoryError, ZstdError,
                 RuntimeError)  # lz4.frame raises RuntimeError on bad data


class McapDamageError(FingerpsReconError):
    """The file is cut short or corrupt at ``offset``; the records before it are intact.

    Attributes
    ----------
    path : Path
        The file.
    offset : int
        Byte offset of the first damaged record (or of the bad magic: 0).
    reason : str
        What is wrong there.
    file_size : int
        Size of the file in bytes.
    chunk_span_ns : tuple[int, int] or None
        Log-time range of the damaged chunk when its header could still be read.
    """

    def __init__(self, path: Path, offset: int, reason: str, file_size: int,
                 chunk_span_ns: tuple[int, int] | None = None) -> None:
        self.path = Path(path)
        self.offset = offset
        self.reason = reason
        self.file_size = file_size
        self.chunk_span_ns = chunk_span_ns
        super().__init__(
            f"{self.path}: damaged at byte offset {offset} of {file_size}: {reason}; the "
            f"records before offset {offset} are intact - 'bag_recover {self.path}' saves them "
            "into a valid bag")


@dataclass(frozen=True)
class ScannedRecord:
    """One record of the data section: where its top-level record starts, and the record.

    Records inside a chunk carry the offset of their chunk.
    """

    offset: int
    record: McapRecord
    in_chunk: bool = False


@dataclass(frozen=True)
class ScanEnd:
    """How the data section ended (the value `scan_records` returns)."""

    offset: int
    """Byte offset just after the last intact record."""
    finished: bool
    """True when the data section ended with a DataEnd record (a finished file)."""


def _parse_one(raw: bytes) -> McapRecord | None:
    records = StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True,
                           record_size_limit=None).records
    return next(iter(records), None)


def _chunk_span(body: bytes) -> tuple[int, int] | None:
    """Log-time range from the first bytes of a (possibly cut) chunk record's body."""
    if len(body) < 16:
        return None
    start, end = struct.unpack_from("<QQ", body)
    return start, end


def scan_records(path: str | os.PathLike[str]) -> Iterator[ScannedRecord]:
    """Yield the data-section records of an MCAP file in file order, chunks opened.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.mcap`` file.

    Yields
    ------
    ScannedRecord
        Schema, Channel, Message, Metadata, Attachment, ... records (Chunk records are
        replaced by their contents; index records are left out).

    Returns
    -------
    ScanEnd
        As the generator's return value (``StopIteration.value``).

    Raises
    ------
    McapDamageError
        At the first record that is cut short or corrupt (or a file that is no MCAP), after
        every intact record before it was yielded.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise McapDamageError(path, 0, "no MCAP magic at the start: not an MCAP file",
                                  size)
        return (yield from _scan_stream(stream, path, size))


def _scan_stream(stream: BinaryIO, path: Path, size: int) -> Iterator[ScannedRecord]:
    offset = len(MAGIC)
    while True:
        if offset == size:
            return ScanEnd(offset=offset, finished=False)
        head = stream.read(_RECORD_HEADER.size)
        if len(head) < _RECORD_HEADER.size:
            raise McapDamageError(path, offset, f"record header cut short ({len(head)} of "
                                  f"{_RECORD_HEADER.size} bytes)", size)
        opcode, length = _RECORD_HEADER.unpack(head)
        end = offset + _RECORD_HEADER.size + length
        if end > size:
            body = stream.read(min(length, 64))
            span = _chunk_span(body) if opcode == Opcode.CHUNK else None
            name = Opcode(opcode).name if opcode in _KNOWN_OPCODES else f"0x{opcode:02x}"
            raise McapDamageError(
                path, offset, f"{name} record of {length} bytes cut short: the file ends "
                f"{end - size} bytes too early", size, span)
        body = stream.read(length)
        if opcode not in _KNOWN_OPCODES:
            offset = end  # unknown records are skipped, as the MCAP spec says
            continue
        try:
            record = _parse_one(head + body)
            inner = (breakup_chunk(record, validate_crc=True)
                     if isinstance(record, Chunk) else None)
        except _PARSE_ERRORS as err:
            span = _chunk_span(body) if opcode == Opcode.CHUNK else None
            raise McapDamageError(path, offset, f"{Opcode(opcode).name} record does not "
                                  f"parse ({type(err).__name__}: {err})", size, span) from None
        if isinstance(record, DataEnd):
            return ScanEnd(offset=end, finished=True)
        if isinstance(record, Footer):  # a file without DataEnd
            return ScanEnd(offset=end, finished=True)
        if inner is not None:
            for item in inner:
                if isinstance(item, (Schema, Channel, Message)):
                    yield ScannedRecord(offset, item, in_chunk=True)
        elif record is not None and opcode not in (Opcode.MESSAGE_INDEX, Opcode.CHUNK_INDEX,
                                                   Opcode.HEADER):
            yield ScannedRecord(offset, record)
        offset = end


def summary_statistics(path: str | os.PathLike[str]) -> Statistics | None:
    """The Statistics record of a finished file's summary, or None (no footer, no summary,
    or anything there unreadable)."""
    path = Path(path)
    size = path.stat().st_size
    if size < len(MAGIC) * 2 + _FOOTER_SIZE:
        return None
    try:
        with open(path, "rb") as stream:
            stream.seek(size - len(MAGIC) - _FOOTER_SIZE)
            tail = stream.read()
            if tail[-len(MAGIC):] != MAGIC:
                return None
            footer = _parse_one(tail[:-len(MAGIC)])
            if not isinstance(footer, Footer) or not 0 < footer.summary_start < size:
                return None
            stream.seek(footer.summary_start)
            summary = stream.read(size - len(MAGIC) - _FOOTER_SIZE - footer.summary_start)
        for record in StreamReader(io.BytesIO(summary), skip_magic=True).records:
            if isinstance(record, Statistics):
                return record
    except _PARSE_ERRORS:
        return None
    return None


__all__ = ["McapDamageError", "ScanEnd", "ScannedRecord", "scan_records", "summary_statistics"]
