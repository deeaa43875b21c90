"""What a recorded session says about itself: its name, the software, the parameters in force.

The recorder writes two MCAP metadata records at the start of every bag:
``fingerps.software`` (`software_record`: package version, ROS distro, RMW, Python, mcap
library, start time) and ``fingerps.recorder.parameters`` (`parameters_record`: every
parameter, strings as they are, other values as JSON).

No rclpy here.
"""

from __future__ import annotations

import json
import os
import platform
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from ament_index_python.packages import get_package_share_directory

PACKAGE = "fingerps_recon"


def default_session_name(now: datetime | None = None) -> str:
    """``fingerps_<UTC date-time>``, e.g. ``fingerps_20250131T120000Z``."""
    now = now or datetime.now(UTC)
    return f"fingerps_{now.astimezone(UTC):%Y%m%dT%H%M%SZ}"


def session_name_problem(value: Any) -> str | None:
    """Why a ``session_name`` is refused (not one directory name), or None."""
    text = str(value)
    if not text or text in (".", "..") or "/" in text or os.sep in text:
        return "must be a single directory name (no '/'), not empty"
    return None


def ros_distro() -> str:
    """The ROS distribution (``ROS_DISTRO``, jazzy when unset)."""
    return os.environ.get("ROS_DISTRO") or "jazzy"


def software_version() -> str:
    """Version of fingerps_recon: its Python distribution, else its package.xml."""
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        pass
    try:
        tree = ET.parse(Path(get_package_share_directory(PACKAGE)) / "package.xml")
        return (tree.getroot().findtext("version") or "unknown").strip()
    except (LookupError, OSError, ET.ParseError, ValueError):
        return "unknown"


def software_record(*, node: str, rmw_implementation: str) -> dict[str, str]:
    """The ``fingerps.software`` record of the recorder ``node`` (fully qualified name)."""
    return {
        "package": PACKAGE,
        "version": software_version(),
        "node": node,
        "ros_distro": ros_distro(),
        "rmw_implementation": rmw_implementation,
        "python": platform.python_version(),
        "mcap": _dist_version("mcap"),
        "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def parameters_record(values: Mapping[str, Any]) -> dict[str, str]:
    """The ``fingerps.recorder.parameters`` record: name -> value, sorted by name."""
    record = {}
    for name in sorted(values):
        value = values[name]
        record[name] = value if isinstance(value, str) else json.dumps(
            list(value) if isinstance(value, (list, tuple)) else value)
    return record


def _dist_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return ""
