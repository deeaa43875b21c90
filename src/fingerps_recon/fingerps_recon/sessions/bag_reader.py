"""Reading a fingerps session bag: messages by topic, deserialised, schemas checked.

`SessionBagReader` reads a bag directory (its ``.mcap`` pieces in order: one, or several
when the recorder split the bag) or an ``.mcap`` file in file order with
`sessions.mcap_records.McapScan`, so it reads finished bags, bags of a killed recorder
(no summary) and damaged ones: a damaged chunk is skipped and reading goes on with the next
intact one (channels defined in a damaged chunk come from the summary), so every intact
message is yielded; then, by default, `McapDamageError` names the damaged byte ranges
(``raise_on_damage=False`` only records them in `SessionBagReader.damage`).

Schema check: the schema text of every ``fingerps_msgs`` type in the bag must equal the full
definition of the installed type (`fingerps_recon.sessions.message_definition`); a bag recorded with
another version of our messages is refused with `BagSchemaError` before any message of that
type is yielded (decoding it with today's classes would give garbage or crash). Types of
other packages (sensor_msgs, ...) are not checked: they are stable within a ROS distro.

Deserialisation uses rclpy's ``deserialize_message`` with the installed message classes.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from importlib import import_module
from typing import Any

from mcap.records import Channel, Message, Schema
from rclpy.serialization import deserialize_message

from fingerps_recon.errors import BagSchemaError, FingerpsReconError, MessageDefinitionError
from fingerps_recon.sessions.bag_recovery import bag_pieces
from fingerps_recon.sessions.mcap_records import DamagedRange, McapScan, damage_error
from fingerps_recon.sessions.message_definition import load_message_definition, split_type_name

CHECKED_PACKAGES = frozenset({"fingerps_msgs"})
"""Packages whose schemas must match the installed definitions."""


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag.

    Attributes
    ----------
    topic : str
        Fully qualified topic name.
    type_name : str
        ``pkg/msg/Type``.
    log_time_ns, publish_time_ns : int
        Receive and source times, ns since the epoch.
    data : bytes
        The serialized (CDR) message.
    offered_qos_yaml : str
        The channel's ``offered_qos_profiles`` metadata.
    """

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    offered_qos_yaml: str = "[]"

    def deserialize(self) -> Any:
        """The message as an instance of its installed rclpy class."""
        return deserialize_message(self.data, message_class(self.type_name))


def message_class(type_name: str) -> type:
    """The installed Python class of ``pkg/msg/Type``.

    Raises
    ------
    FingerpsReconError
        When the package is not built or has no such type.
    """
    package, name = split_type_name(type_name)
    try:
        return getattr(import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError) as err:
        raise FingerpsReconError(
            f"cannot import message type {type_name}: {err}; build the workspace (make build) "
            "and source tools/ros_env.sh") from None


def check_schema(schema_name: str, schema_text: str, *, source: str = "the bag") -> None:
    """Refuse a schema of a checked package that differs from the installed definition.

    Raises
    ------
    BagSchemaError
        Naming the type and the first differing line.
    """
    try:
        package, _ = split_type_name(schema_name)
    except MessageDefinitionError:
        return
    if package not in CHECKED_PACKAGES:
        return
    try:
        installed = load_message_definition(schema_name).text
    except MessageDefinitionError as err:
        raise BagSchemaError(f"{source} holds {schema_name}, which is not installed: {err}") \
            from None
    if installed == schema_text:
        return
    diff = [("installed: " if line[0] == "-" else "bag: ") + line[1:].split("#")[0].strip()
            for line in difflib.unified_diff(installed.splitlines(), schema_text.splitlines(),
                                             n=0, lineterm="")
            if line[:1] in "+-" and not line.startswith(("+++", "---"))]
    shown = "; ".join(d for d in diff if not d.endswith(": "))[:300] or "(whitespace only)"
    raise BagSchemaError(
        f"{source} was recorded with another version of {schema_name} than the one installed "
        f"(schema differs: {shown}); read it with the fingerps version that recorded it (its "
        "'fingerps.software' metadata record names it), or rebuild with that message "
        "definition")


class SessionBagReader:
    """Reads the messages of a session bag in file order.

    Parameters
    ----------
    path : str or os.PathLike
        A bag directory (every piece, in order: `fingerps_recon.sessions.bag_recovery.bag_pieces`)
        or an ``.mcap`` file.
    check_schemas : bool
        Refuse fingerps_msgs schemas that differ from the installed ones (`check_schema`).
    raise_on_damage : bool
        After the last intact message of a damaged file, raise `McapDamageError` (default);
        with False the damage is only recorded in `damage` and `orphaned_messages`.
    """

    def __init__(self, path: str | os.PathLike[str], *, check_schemas: bool = True,
                 raise_on_damage: bool = True) -> None:
        self.mcap_paths = bag_pieces(path)
        self.mcap_path = self.mcap_paths[0]
        self._check = check_schemas
        self._raise = raise_on_damage
        self._scans: list[McapScan] = []

    @property
    def damage(self) -> tuple[DamagedRange, ...]:
        """Damaged byte ranges met by the last complete `messages` pass (empty before), in
        piece order; each error names its file."""
        return tuple(d for scan in self._scans for d in scan.damage)

    @property
    def orphaned_messages(self) -> int:
        """Intact messages of the last pass whose channel is defined nowhere readable."""
        return sum(sum(scan.orphans.values()) for scan in self._scans)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Yield the messages (of the given topics only, when given) in file order.

        Damaged chunks are skipped; reading resumes at the next intact chunk.

        Raises
        ------
        BagSchemaError
            At the first schema of ours that differs from the installed definition.
        McapDamageError
            After the last intact message of a damaged file (unless ``raise_on_damage`` is
            False), naming every damaged byte range.
        """
        wanted = None if topics is None else set(topics)
        scans = []
        for mcap_path in self.mcap_paths:
            scan = McapScan(mcap_path)
            yield from self._piece_messages(scan, wanted)
            scans.append(scan)
        self._scans = scans
        damaged = [scan for scan in scans if scan.damage or scan.orphans]
        if self._raise and damaged:
            raise damage_error(damaged[0])

    def _piece_messages(self, scan: McapScan, wanted: set[str] | None) -> Iterator[BagMessage]:
        """The messages of one MCAP file (schema and channel ids are the file's own)."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for item in scan:
            record = item.record
            if isinstance(record, Schema):
                if self._check:
                    check_schema(record.name, record.data.decode("utf-8", errors="replace"),
                                 source=str(scan.path))
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None or (wanted is not None and channel.topic not in wanted):
                    continue
                schema = schemas.get(channel.schema_id)
                yield BagMessage(
                    topic=channel.topic, type_name=schema.name if schema else "",
                    log_time_ns=record.log_time, publish_time_ns=record.publish_time,
                    data=record.data,
                    offered_qos_yaml=channel.metadata.get("offered_qos_profiles", "[]"))

    def topics(self) -> dict[str, str]:
        """Topic -> type name of every channel of every piece, damaged chunks' ones from the
        summary (reads a whole piece unless its summary is intact)."""
        found: dict[str, str] = {}
        for mcap_path in self.mcap_paths:
            scan = McapScan(mcap_path)
            summary = scan.summary
            if summary.source == "footer" and summary.channels:
                for ch in summary.channels.values():
                    found.setdefault(ch.topic, summary.schemas[ch.schema_id].name
                                     if ch.schema_id in summary.schemas else "")
                continue
            schemas: dict[int, str] = {}
            for item in scan:
                record = item.record
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    found.setdefault(record.topic, schemas.get(record.schema_id, ""))
        return found

    def latest(self, topic: str) -> Any | None:
        """The last message of a topic, deserialised; None when the bag has none."""
        last = None
        for message in self.messages([topic]):
            last = message
        return None if last is None else last.deserialize()

