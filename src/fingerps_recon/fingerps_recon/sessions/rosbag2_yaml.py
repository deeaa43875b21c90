"""YAML as rosbag2 writes it (yaml-cpp's ``YAML::Dump``: block style, 2-space indent,
sequences indented under their key), for metadata.yaml, the ``rosbag2`` MCAP record and the
channels' ``offered_qos_profiles``: byte for byte what ``ros2 bag`` writes, which PyYAML's
emitter (flow style, other quoting and indentation) does not give. PyYAML reads it back.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

_PLAIN = re.compile(r"[A-Za-z0-9_/][A-Za-z0-9_./-]*")


def yaml_scalar(value: Any) -> str:
    """One scalar (or an empty collection) as yaml-cpp writes it: plain when it reads back
    as the same string, else double-quoted."""
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, dict):
        return "{}"
    if isinstance(value, list):
        return "[]"
    text = str(value)
    if _PLAIN.fullmatch(text) and yaml.safe_load(text) == text:
        return text
    # A double-quoted JSON string is a valid YAML double-quoted scalar.
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    escaped = escaped.replace("\t", "\\t").replace("\r", "\\r")
    return f'"{escaped}"'


def yaml_lines(value: Any, indent: int = 0) -> list[str]:
    """``value`` (dicts, lists, scalars) as yaml-cpp's ``YAML::Dump`` writes it: the lines,
    each ``indent`` spaces in."""
    pad = " " * indent
    lines: list[str] = []
    if isinstance(value, dict) and value:
        for key, item in value.items():
            if isinstance(item, (dict, list)) and item:
                lines.append(f"{pad}{yaml_scalar(key)}:")
                lines.extend(yaml_lines(item, indent + 2))
            else:
                lines.append(f"{pad}{yaml_scalar(key)}: {yaml_scalar(item)}")
    elif isinstance(value, list) and value:
        for item in value:
            if isinstance(item, (dict, list)) and item:
                sub = yaml_lines(item, indent + 2)
                lines.append(f"{pad}- {sub[0][indent + 2:]}")
                lines.extend(sub[1:])
            else:
                lines.append(f"{pad}- {yaml_scalar(item)}")
    else:
        lines.append(pad + yaml_scalar(value))
    return lines
