"""Full ROS 2 message definitions, as rosbag2 writes them into MCAP schemas.

A ROS 2 MCAP file (profile ``ros2``) carries, for every message type, a Schema record whose
data is the type's *full* definition: the type's own ``.msg`` text followed by the text of
every type it uses, nested ones included, so a reader can decode the messages without the
ROS packages installed. This module builds that text exactly as rosbag2 (Jazzy) does in
``rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp``:

- the top-level ``share/<pkg>/msg/<Type>.msg`` file, byte for byte (comments, constants and
  blank lines kept);
- then, depth first, for each dependency not yet written (the dependencies of one file in
  sorted order, each type once in the whole text), ``"\\n"``, a line of 80 ``=``, a line
  ``MSG: <pkg>/<Type>`` (the name as the field declares it, a package-less name prefixed
  with the package of the file it appears in) and that type's ``.msg`` text;
- a type without a ``.msg`` anywhere in the tree falls back to the ``.idl`` files: every
  section, the first one included, then starts with the separator and ``IDL: <pkg>/msg/<T>``,
  and the encoding is ``ros2idl`` instead of ``ros2msg``.

The type hash (REP-2011, ``RIHS01_...``) that rosbag2 stores as ``type_description_hash`` is
read from the ``share/<pkg>/msg/<Type>.json`` file that rosidl generates next to the
``.msg``; it is the hash the publishers announce in the graph.

No rclpy here: only ``ament_index_python`` to find the packages' share directories.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

from fingerps_recon.errors import MessageDefinitionError

SEPARATOR = "=" * 80
"""The line between two types in a full definition (without its newline)."""

MAX_RECURSION_DEPTH = 50
"""Nesting depth at which rosbag2 gives up (a type including itself)."""

ENCODING_MSG = "ros2msg"
ENCODING_IDL = "ros2idl"

# The three regular expressions of local_message_definition_source.cpp. Its std::regex is
# ECMAScript with char: \s is [ \t\n\v\f\r], as Python's with re.ASCII; ^ matches at the
# start of the text only, as Python's without re.MULTILINE.
_PACKAGE_TYPENAME = re.compile(r"^([a-zA-Z0-9_]+)/(?:msg/|srv/)?([a-zA-Z0-9_]+)$", re.ASCII)
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+", re.ASCII)
_IDL_FIELD_TYPE = re.compile(
    r"(?:^|\n)#include\s+(?:\"|<)([a-zA-Z0-9_/]+)\.idl(?:\"|>)", re.ASCII
)

PRIMITIVE_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8",
    "int16", "uint16", "int32", "uint32", "int64", "uint64", "string",
})


class _DefinitionNotFoundError(Exception):
    """Internal: no file of the asked format; rosbag2 then falls back to IDL."""


@dataclass(frozen=True)
class MessageDefinition:
    """The full definition of one message type, as stored in an MCAP Schema record.

    Attributes
    ----------
    type_name : str
        The name the definition was asked for, e.g. ``"fingerps_msgs/msg/Burst"``; rosbag2
        uses it as the schema name.
    encoding : str
        ``"ros2msg"`` or ``"ros2idl"``: the schema encoding.
    text : str
        The full definition text (UTF-8 when written as the schema data).
    """

    type_name: str
    encoding: str
    text: str


def split_type_name(type_name: str) -> tuple[str, str]:
    """Split ``pkg/msg/Type`` (or ``pkg/Type``) into ``(pkg, Type)``.

    Raises
    ------
    MessageDefinitionError
        When the name is not of that form.
    """
    match = _PACKAGE_TYPENAME.match(type_name)
    if match is None or "/srv/" in type_name:
        raise MessageDefinitionError(
            f"message type name {type_name!r} not understood: write it as "
            "'package/msg/Type', e.g. 'sensor_msgs/msg/Image'")
    return match.group(1), match.group(2)


def _share_dir(package: str, type_name: str) -> Path:
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError) as err:
        raise MessageDefinitionError(
            f"no definition for {type_name!r}: package {package!r} is not in the ament index "
            "(AMENT_PREFIX_PATH); build the workspace (make build) and source "
            "tools/ros_env.sh") from err


def _load_text(type_name: str, extension: str) -> tuple[str, str]:
    """Return (package, file text) of ``share/<pkg>/msg/<Type><extension>``."""
    package, name = split_type_name(type_name)
    path = _share_dir(package, type_name) / "msg" / f"{name}{extension}"
    try:
        data = path.read_bytes()
    except OSError as err:
        raise _DefinitionNotFoundError(type_name) from err
    return package, data.decode("utf-8")


def _dependencies(text: str, package: str, encoding: str) -> list[str]:
    """Types a definition uses, sorted as rosbag2's std::set<std::string> sorts them."""
    if encoding == ENCODING_MSG:
        found = set()
        for match in _MSG_FIELD_TYPE.finditer(text):
            field_type = match.group(1)
            if field_type in PRIMITIVE_TYPES:
                continue
            found.add(field_type if "/" in field_type else f"{package}/{field_type}")
    else:
        found = {match.group(1) for match in _IDL_FIELD_TYPE.finditer(text)}
    return sorted(found, key=lambda name: name.encode("utf-8"))


def _delimiter(type_name: str, encoding: str) -> str:
    kind = "MSG" if encoding == ENCODING_MSG else "IDL"
    return f"{SEPARATOR}\n{kind}: {type_name}\n"


def _full_text(root: str, encoding: str) -> str:
    extension = ".msg" if encoding == ENCODING_MSG else ".idl"
    seen: set[str] = set()

    def append_recursive(type_name: str, depth: int) -> str:
        if depth <= 0:
            raise MessageDefinitionError(
                f"definition of {root!r} nests deeper than {MAX_RECURSION_DEPTH} types; "
                "a message type must not contain itself")
        package, text = _load_text(type_name, extension)
        result = text
        for dependency in _dependencies(text, package, encoding):
            if dependency not in seen:
                seen.add(dependency)
                result += "\n" + _delimiter(dependency, encoding)
                result += append_recursive(dependency, depth - 1)
        return result

    if encoding == ENCODING_MSG:
        return append_recursive(root, MAX_RECURSION_DEPTH)
    return _delimiter(root, encoding) + append_recursive(root, MAX_RECURSION_DEPTH)


def load_message_definition(type_name: str) -> MessageDefinition:
    """Build the full definition of a message type from the installed interface files.

    Parameters
    ----------
    type_name : str
        ``"pkg/msg/Type"`` (the ROS 2 form, used as the MCAP schema name) or ``"pkg/Type"``.

    Returns
    -------
    MessageDefinition
        The definition rosbag2 would write: ``ros2msg`` when every type involved has a
        ``.msg`` file, else ``ros2idl``.

    Raises
    ------
    MessageDefinitionError
        When the name is malformed, its package is not installed, or neither a ``.msg`` nor an
        ``.idl`` definition of it (or of a type it uses) exists.
    """
    split_type_name(type_name)
    try:
        return MessageDefinition(type_name, ENCODING_MSG, _full_text(type_name, ENCODING_MSG))
    except _DefinitionNotFoundError:
        pass
    try:
        return MessageDefinition(type_name, ENCODING_IDL, _full_text(type_name, ENCODING_IDL))
    except _DefinitionNotFoundError as err:
        raise MessageDefinitionError(
            f"no .msg or .idl definition of {err.args[0]!r} (needed for {type_name!r}) in its "
            "package's share/<pkg>/msg directory; is the package built with rosidl?") from None


def message_definition(type_name: str) -> str:
    """Full definition text of a message type, exactly as rosbag2 writes it into a schema.

    Parameters
    ----------
    type_name : str
        ``"pkg/msg/Type"``, e.g. ``"fingerps_msgs/msg/Burst"``.

    Returns
    -------
    str
        The ``ros2msg`` text (the ``ros2idl`` text for types that only have ``.idl`` files;
        `load_message_definition` tells which).
    """
    return load_message_definition(type_name).text


def type_description_hash(type_name: str) -> str:
    """The REP-2011 type hash (``"RIHS01_<64 hex>"``) of a message type, or ``""``.

    Read from ``share/<pkg>/msg/<Type>.json`` (generated by rosidl_generator_type_description);
    ``""`` when that file is absent or does not list the type, as rosbag2 writes when a hash
    is unknown.
    """
    package, name = split_type_name(type_name)
    path = _share_dir(package, type_name) / "msg" / f"{name}.json"
    try:
        description = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    full_name = f"{package}/msg/{name}"
    for entry in description.get("type_hashes", []):
        if entry.get("type_name") == full_name:
            return str(entry.get("hash_string", ""))
    return ""
