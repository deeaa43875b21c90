"""A rosbag2-compatible MCAP bag writer (pure Python, no rclpy).

`SessionBagWriter` writes serialized (CDR) messages into a bag directory laid out as
``ros2 bag record -s mcap -o DIR`` (rosbag2 Jazzy) lays it out::

    DIR/
      DIR_0.mcap       # MCAP, profile "ros2", chunked and zstd-compressed, with summary
      DIR_1.mcap ...   # further pieces when the bag is split (max_bagfile_size/duration)
      metadata.yaml    # rosbag2_bagfile_information, version 9, written by finish()

so ``ros2 bag info/play``, rosbags, Foxglove and the ``mcap`` tools read it. What matches
rosbag2 Jazzy (rosbag2_storage_mcap/src/mcap_storage.cpp, rosbag2_cpp writers/
sequential_writer.cpp, rosbag2_storage yaml.hpp and qos.cpp):

- one Schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``, data the full
  definition of `fingerps_recon.sessions.message_definition`;
- one Channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles`` (the
  YAML of `qos_profiles_yaml`) and ``topic_type_hash`` (REP-2011 hash, or ``""``);
- Message records with log time = receive time and publish time = source time (ns);
- a Metadata record ``rosbag2`` whose ``serialized_metadata`` is the bag metadata YAML, as
  rosbag2's ``update_metadata`` writes it on close;
- ``metadata.yaml``: version 9, storage_identifier ``mcap``, duration, starting_time,
  message_count, topics_with_message_count (offered QoS as a YAML list, version-9 style,
  type_description_hash), compression_format/mode ``""`` (the compression is inside the MCAP
  chunks, as with rosbag2's ``zstd_fast`` preset), relative_file_paths, files, custom_data,
  ros_distro.

Splitting, as rosbag2's ``max_bagfile_size`` / ``max_bagfile_duration``: before a message
is written, the open piece is finished (summary and ``rosbag2`` record) and ``DIR_<n+1>.mcap``
begun when the piece already holds a message and its size on disk has reached
``max_bagfile_size`` bytes, or the message's log time is ``max_bagfile_duration`` or more past
the piece's first message (0 = no limit). Every piece is a complete MCAP file on its own:
each repeats the Schema, Channel and Metadata records, so a piece can be read, copied or
deleted alone. metadata.yaml lists every piece in ``relative_file_paths`` and ``files``.
Sizes count what reached the file, so a piece ends at most one chunk past the limit.

Differences from rosbag2: a topic enters the bag when it is added (the recorder adds it at
its first message); CRCs of chunks are written (rosbag2 leaves them out).

Crash behaviour: messages gather in an open chunk of at most ``chunk_size`` bytes
(`DEFAULT_CHUNK_SIZE`, 4 MiB); a full chunk is compressed and handed to the operating system
at once (the file is unbuffered), so a killed process loses at most the open chunk (plus the
summary and metadata.yaml, which ``bag_recover`` (`fingerps_recon.sessions.bag_recovery`) rebuilds).
`SessionBagWriter.flush` closes the open chunk early; call it periodically to bound the loss
in time as well.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer

from fingerps_recon.errors import MessageDefinitionError, SessionBagError
from fingerps_recon.sessions.bag_metadata import (
    INT64_MAX,
    METADATA_FILENAME,
    BagPiece,
    BagSummary,
    bag_metadata,
)
from fingerps_recon.sessions.message_definition import (
    MessageDefinition,
    load_message_definition,
    type_description_hash,
)
from fingerps_recon.sessions.rosbag2_yaml import yaml_lines
from fingerps_recon.sessions.zstd_level import use_zstd_level

PROFILE = "ros2"
SERIALIZATION_FORMAT = "cdr"
ROSBAG2_METADATA_RECORD = "rosbag2"
DEFAULT_CHUNK_SIZE = 4 * 1024 * 1024
"""Bytes of messages per chunk: the most a killed recorder loses, and the compression unit."""



class Compression(Enum):
    """Compression of the MCAP chunks."""

    ZSTD = "zstd"
    LZ4 = "lz4"
    NONE = ""


_MCAP_COMPRESSION = {
    Compression.ZSTD: CompressionType.ZSTD,
    Compression.LZ4: CompressionType.LZ4,
    Compression.NONE: CompressionType.NONE,
}

# ---- the writer ------------------------------------------------------------------------------


class _UnbufferedFile:
    """A write-only file with no user-space buffer, for mcap's Writer.

    mcap hands over whole records (a full chunk at a time), so writing them straight to the
    OS costs little and leaves nothing behind in Python buffers if the process is killed.
    """

    def __init__(self, path: Path) -> None:
        # 0o666 less the umask: owner-only under the nodes' 077 (fingerps_ros.privacy)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        self._position = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view.nbytes:
            written = os.write(self._fd, view)
            view = view[written:]
        self._position += len(data)
        return len(data)

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        """Nothing to do: every write already reached the OS."""

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)


@dataclass
class _Topic:
    name: str
    type_name: str
    serialization_format: str
    offered_qos: list[Any]
    type_hash: str
    channel_id: int
    definition: MessageDefinition
    channel_metadata: dict[str, str]
    message_count: int = 0


class SessionBagWriter:
    """Writes serialized ROS 2 messages into a rosbag2 MCAP bag directory.

    Use ``start()`` ... ``finish()`` or ``with SessionBagWriter(path) as bag:``. Methods are
    thread-safe (one lock), so intake and writing may run on different threads.

    Parameters
    ----------
    path : str or os.PathLike
        The bag directory to create; it must not exist (its parents are created).
    chunk_size : int
        Uncompressed bytes per MCAP chunk; see the module docstring.
    compression : Compression
        Chunk compression, zstd by default.
    ros_distro : str
        Written as ``ros_distro`` in the metadata.
    custom_data : Mapping[str, str], optional
        rosbag2's ``custom_data`` of metadata.yaml.
    library : str, optional
        The MCAP header's library string.
    max_bagfile_size : int
        Split into a new MCAP file once a piece has reached this many bytes (0: never).
    max_bagfile_duration_ns : int
        Split once a message is this long after the piece's first message (0: never).

    Examples
    --------
    >>> with SessionBagWriter(tmp / "session") as bag:               # doctest: +SKIP
    ...     bag.add_topic("/chatter", "std_msgs/msg/String",
    ...                   offered_qos_yaml=qos_profiles_yaml(QosProfileFields()))
    ...     bag.write("/chatter", data, log_time_ns=t, publish_time_ns=t)
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: Compression = Compression.ZSTD,
        ros_distro: str = "jazzy",
        custom_data: Mapping[str, str] | None = None,
        library: str | None = None,
        max_bagfile_size: int = 0,
        max_bagfile_duration_ns: int = 0,
    ) -> None:
        if chunk_size <= 0:
            raise SessionBagError(f"chunk_size must be positive, got {chunk_size}")
        if max_bagfile_size < 0 or max_bagfile_duration_ns < 0:
            raise SessionBagError(
                f"max_bagfile_size ({max_bagfile_size}) and max_bagfile_duration_ns "
                f"({max_bagfile_duration_ns}) must be 0 (no splitting) or positive")
        self._path = Path(path)
        name = self._path.resolve().name if self._path.name in ("", ".", "..") else self._path.name
        self._base_name = name
        self._file_name = f"{name}_0.mcap"
        self._max_size = int(max_bagfile_size)
        self._max_duration_ns = int(max_bagfile_duration_ns)
        self._pieces: list[BagPiece] = []
        self._piece_first_ns: int | None = None
        self._piece_last_ns: int | None = None
        self._piece_messages = 0
        self._metadata_records: list[tuple[str, dict[str, str]]] = []
        self._chunk_size = int(chunk_size)
        self._compression = Compression(compression)
        self._ros_distro = ros_distro
        self._custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self._library = library or f"fingerps_recon session_bag; {LIBRARY_IDENTIFIER}"
        self._lock = threading.Lock()
        self._file: _UnbufferedFile | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _Topic] = {}
        self._first_log_ns: int | None = None
        self._last_log_ns: int | None = None
        self._summary: BagSummary | None = None

    # -- properties ----------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The bag directory."""
        return self._path

    @property
    def mcap_path(self) -> Path:
        """The MCAP file being written, ``<dir>/<dir name>_<n>.mcap`` as rosbag2 names it."""
        return self._path / self._file_name

    @property
    def pieces(self) -> tuple[BagPiece, ...]:
        """The finished MCAP files of the bag so far (the open one is not among them)."""
        with self._lock:
            return tuple(self._pieces)

    @property
    def bytes_written(self) -> int:
        """Bytes of every piece so far, the open one included."""
        with self._lock:
            open_bytes = self._file.tell() if self._file is not None else 0
            return sum(p.size_bytes for p in self._pieces) + open_bytes

    @property
    def is_open(self) -> bool:
        """True between start() and finish()."""
        return self._writer is not None

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        with self._lock:
            return {name: topic.message_count for name, topic in self._topics.items()}

    def has_topic(self, topic: str) -> bool:
        """Whether `add_topic` was called for this topic."""
        with self._lock:
            return topic in self._topics

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        """Create the bag directory and the MCAP file and write its header.

        Raises
        ------
        SessionBagError
            When the directory exists or cannot be created, or start() was called before.
        """
        with self._lock:
            if self._writer is not None or self._summary is not None:
                raise SessionBagError(
                    f"bag {self._path} was already started; create a new SessionBagWriter "
                    "for another bag")
            if self._path.exists():
                raise SessionBagError(
                    f"bag directory {self._path} already exists; choose another session name "
                    "or bags directory, or remove the old bag")
            try:
                self._path.mkdir(parents=True)
            except OSError as err:
                raise SessionBagError(
                    f"cannot create bag directory {self._path}: {err.strerror or err}; "
                    "choose a writable bags directory") from None
            self._open_piece()

    def _open_piece(self) -> None:
        """Create the MCAP file ``self._file_name``, write its header and every schema,
        channel and metadata record added so far (lock held)."""
        try:
            self._file = _UnbufferedFile(self.mcap_path)
        except OSError as err:
            raise SessionBagError(
                f"cannot create {self.mcap_path}: {err.strerror or err}; "
                "check the bags directory's permissions and free space") from None
        use_zstd_level()  # the chunks at zstd level 1, as ros2 bag record writes them
        self._writer = Writer(
            self._file,  # type: ignore[arg-type]  # duck-typed stream
            chunk_size=self._chunk_size,
            compression=_MCAP_COMPRESSION[self._compression],
            index_types=IndexType.ALL,
            repeat_channels=True,
            repeat_schemas=True,
            use_chunking=True,
            use_statistics=True,
            use_summary_offsets=True,
        )
        self._guarded(lambda w: w.start(profile=PROFILE, library=self._library))
        self._schemas = {}
        self._piece_first_ns = self._piece_last_ns = None
        self._piece_messages = 0
        for topic in self._topics.values():
            topic.channel_id = self._register(topic.type_name, topic.definition,
                                              topic.name, topic.serialization_format,
                                              topic.channel_metadata)
        for name, record in self._metadata_records:
            self._guarded(lambda w, n=name, r=record: w.add_metadata(n, r))

    def _register(self, type_name: str, definition: MessageDefinition, topic: str,
                  serialization_format: str, metadata: dict[str, str]) -> int:
        """Schema (once per type and file) and Channel of a topic; returns the channel id."""
        schema_id = self._schemas.get(type_name)
        if schema_id is None:
            schema_id = self._guarded(lambda w: w.register_schema(
                name=type_name, encoding=definition.encoding,
                data=definition.text.encode("utf-8")))
            self._schemas[type_name] = schema_id
        return self._guarded(lambda w: w.register_channel(
            topic=topic, message_encoding=serialization_format, schema_id=schema_id,
            metadata=metadata))

    def _open_piece_entry(self, size_bytes: int = 0) -> BagPiece:
        first = self._piece_first_ns
        return BagPiece(
            path=self.mcap_path, starting_time_ns=INT64_MAX if first is None else first,
            duration_ns=0 if first is None else int(self._piece_last_ns) - first,
            message_count=self._piece_messages, size_bytes=size_bytes)

    def _close_piece(self, writer: Writer) -> None:
        """Write the ``rosbag2`` record (the bag so far) and the summary of the open piece,
        close its file, and list it among the pieces (lock held)."""
        try:
            metadata = self._bag_metadata(self._make_summary(),
                                          [*self._pieces, self._open_piece_entry()])
            serialized = "\n".join(yaml_lines(metadata))
            writer.add_metadata(ROSBAG2_METADATA_RECORD, {"serialized_metadata": serialized})
            writer.finish()
        except OSError as err:
            raise SessionBagError(
                f"cannot finish {self.mcap_path}: {err.strerror or err}; the data written "
                "so far can be saved with 'bag_recover'") from None
        finally:
            if self._file is not None:
                self._file.close()
            self._pieces.append(self._open_piece_entry(
                self._file.tell() if self._file is not None else 0))
            self._file = None

    def _split(self) -> None:
        """Finish the open piece and begin the next (lock held)."""
        writer, self._writer = self._writer, None
        self._close_piece(writer)
        self._file_name = f"{self._base_name}_{len(self._pieces)}.mcap"
        self._open_piece()

    def _should_split(self, log_time_ns: int) -> bool:
        if self._piece_messages == 0 or self._file is None or self._writer is None:
            return False
        if self._max_size and self._file.tell() >= self._max_size:
            return True
        return bool(self._max_duration_ns
                    and log_time_ns - int(self._piece_first_ns) >= self._max_duration_ns)

    def finish(self) -> BagSummary:
        """Close the open chunk, write summary, ``rosbag2`` metadata record and metadata.yaml.

        Safe to call more than once (later calls return the first call's summary) and
        before start() (then nothing is written).

        Returns
        -------
        BagSummary
            Paths and message counts.
        """
        with self._lock:
            if self._summary is not None:
                return self._summary
            writer, self._writer = self._writer, None
            if writer is None and not self._pieces:  # never started
                self._summary = self._make_summary()
                return self._summary
            try:
                if writer is not None:
                    self._close_piece(writer)
            finally:
                self._summary = self._make_summary()
            summary = self._summary
            metadata = self._bag_metadata(summary, self._pieces)
            document = {"rosbag2_bagfile_information": metadata}
            text = "\n".join(yaml_lines(document))
            target = self._path / METADATA_FILENAME
            partial = self._path / (METADATA_FILENAME + ".partial")
            try:
                partial.write_text(text, encoding="utf-8")
                os.replace(partial, target)
            except OSError as err:
                raise SessionBagError(
                    f"cannot write {target}: {err.strerror or err}; the MCAP file is complete, "
                    "'ros2 bag reindex' recreates the metadata") from None
            return summary

    def __enter__(self) -> SessionBagWriter:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.finish()

    # -- content -------------------------------------------------------------------------------

    def add_topic(
        self,
        topic: str,
        type_name: str,
        *,
        offered_qos_yaml: str,
        serialization_format: str = SERIALIZATION_FORMAT,
        type_hash: str | None = None,
        definition: MessageDefinition | None = None,
    ) -> None:
        """Register a topic: its Schema (once per type) and Channel.

        Parameters
        ----------
        topic : str
            Fully qualified topic name, e.g. ``"/fingerps/burst"``.
        type_name : str
            ``"pkg/msg/Type"``; its definition must be installed (ament index).
        offered_qos_yaml : str
            The publishers' QoS profiles, from `qos_profiles_yaml` (``"[]"`` or ``""`` when
            unknown).
        serialization_format : str
            ``"cdr"`` for ROS 2 messages.
        type_hash : str, optional
            REP-2011 hash; by default read from the installed interface description.
        definition : MessageDefinition, optional
            The schema to write (e.g. one copied from another bag, as ``bag_recover`` does);
            by default the installed full definition of ``type_name``.

        Raises
        ------
        SessionBagError
            Bag not open, topic already added, definition not found, bad QoS YAML.
        """
        try:
            profiles = yaml.safe_load(offered_qos_yaml) if offered_qos_yaml.strip() else []
        except yaml.YAMLError as err:
            raise SessionBagError(
                f"offered_qos_yaml of {topic} is not YAML ({err}); build it with "
                "qos_profiles_yaml()") from None
        if not isinstance(profiles, list) or not all(isinstance(p, dict) for p in profiles):
            raise SessionBagError(
                f"offered_qos_yaml of {topic} must be a YAML list of QoS mappings; build it "
                "with qos_profiles_yaml()")
        try:
            if definition is None:
                definition = load_message_definition(type_name)
            if type_hash is None:
                type_hash = type_description_hash(type_name)
        except MessageDefinitionError as err:
            raise SessionBagError(f"cannot add topic {topic}: {err}") from None
        channel_qos = "\n".join(yaml_lines(profiles)) if profiles else "[]"
        metadata = {"offered_qos_profiles": channel_qos, "topic_type_hash": type_hash}
        with self._lock:
            self._require_open()
            if topic in self._topics:
                raise SessionBagError(f"topic {topic} was already added to {self._path}")
            channel_id = self._register(type_name, definition, topic, serialization_format,
                                        metadata)
            self._topics[topic] = _Topic(
                name=topic, type_name=type_name, serialization_format=serialization_format,
                offered_qos=profiles, type_hash=type_hash, channel_id=channel_id,
                definition=definition, channel_metadata=metadata)

    def write(
        self,
        topic: str,
        data: bytes,
        *,
        log_time_ns: int,
        publish_time_ns: int,
        sequence: int = 0,
    ) -> None:
        """Append one serialized message.

        Parameters
        ----------
        topic : str
            A topic registered with `add_topic`.
        data : bytes
            The serialized message (CDR, with its 4-byte encapsulation header).
        log_time_ns : int
            Receive time, ns since the epoch (rosbag2's ``recv_timestamp``).
        publish_time_ns : int
            Source (send) time, ns since the epoch.
        sequence : int
            Optional publisher sequence number (rosbag2 writes 0).
        """
        with self._lock:
            self._require_open()
            entry = self._topics.get(topic)
            if entry is None:
                raise SessionBagError(
                    f"topic {topic} is not in bag {self._path}; call add_topic() before write()")
            log_time_ns = int(log_time_ns)
            if self._should_split(log_time_ns):
                self._split()
            self._guarded(lambda w: w.add_message(
                channel_id=entry.channel_id, log_time=log_time_ns, data=data,
                publish_time=int(publish_time_ns), sequence=int(sequence)))
            entry.message_count += 1
            self._piece_messages += 1
            if self._piece_first_ns is None or log_time_ns < self._piece_first_ns:
                self._piece_first_ns = log_time_ns
            if self._piece_last_ns is None or log_time_ns > self._piece_last_ns:
                self._piece_last_ns = log_time_ns
            if self._first_log_ns is None or log_time_ns < self._first_log_ns:
                self._first_log_ns = log_time_ns
            if self._last_log_ns is None or log_time_ns > self._last_log_ns:
                self._last_log_ns = log_time_ns

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write an MCAP Metadata record (e.g. software version, parameters, calibration).

        Raises
        ------
        SessionBagError
            Bag not open, reserved name ``rosbag2``, or keys/values that are not strings.
        """
        if name == ROSBAG2_METADATA_RECORD:
            raise SessionBagError(
                f"metadata name {name!r} is reserved for rosbag2's own record; use another name")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise SessionBagError(
                f"metadata {name!r} must map strings to strings; convert values with str()")
        record = dict(data)
        with self._lock:
            self._require_open()
            self._guarded(lambda w: w.add_metadata(name, record))
            self._metadata_records.append((name, record))  # repeated in later pieces

    def set_custom_data(self, key: str, value: str) -> None:
        """Set one entry of metadata.yaml's ``custom_data`` (written by finish())."""
        with self._lock:
            self._custom_data[str(key)] = str(value)

    def flush(self) -> None:
        """Close the open chunk (if it holds messages) and hand it to the OS."""
        with self._lock:
            if self._writer is not None:
                self._guarded(lambda w: w.flush())

    # -- internals -----------------------------------------------------------------------------

    def _require_open(self) -> Writer:
        if self._writer is None:
            state = "finished" if self._summary is not None else "not started"
            raise SessionBagError(f"bag {self._path} is {state}; write between start() and "
                                  "finish()")
        return self._writer

    def _guarded(self, action: Any) -> Any:
        writer = self._require_open()
        try:
            return action(writer)
        except OSError as err:
            raise SessionBagError(
                f"writing {self.mcap_path} failed: {err.strerror or err}; free disk space or "
                "choose another bags directory") from None

    def _make_summary(self) -> BagSummary:
        counts = {name: topic.message_count for name, topic in self._topics.items()}
        first = self._first_log_ns
        return BagSummary(
            path=self._path,
            mcap_path=self._path / f"{self._base_name}_0.mcap",
            pieces=tuple(self._pieces),
            message_counts=counts,
            message_count=sum(counts.values()),
            starting_time_ns=INT64_MAX if first is None else first,
            duration_ns=0 if first is None else int(self._last_log_ns) - first,
        )

    def _bag_metadata(self, summary: BagSummary, pieces: list[BagPiece]) -> dict[str, Any]:
        return bag_metadata(summary, pieces, self._topics.values(),
                            custom_data=self._custom_data, ros_distro=self._ros_distro)
