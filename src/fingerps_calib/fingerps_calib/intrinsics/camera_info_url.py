"""Where a camera's calibration lives: camera_info_manager's URLs, resolved and written.

The rules are those of ``camera_info_manager`` (ros-perception/image_common, jazzy), which
``usb_cam``, ``v4l2_camera`` and the other ROS camera drivers use, so a calibration made
for one of them is found by fingerps the same way:

- ``""`` (empty): the default, ``file://${ROS_HOME}/camera_info/${NAME}.yaml``;
- ``file:///absolute/path.yaml``;
- ``package://<package>/<path in its share directory>``;
- ``${NAME}`` is the camera name, ``${ROS_HOME}`` is ``$ROS_HOME`` or else ``$HOME/.ros``;
  a ``$`` not followed by ``{`` stays as it is.

Scheme names are matched without regard to case, as there. ``flash:///`` (the camera's
own memory) is recognised and refused: no fingerps camera has one. A camera name may hold
only letters, digits and ``_`` (``camera_info_manager``'s ``setCameraName``).

No ROS graph is needed here: `package://` is looked up in the ament index
(``ament_index_python``, importable without a running node).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, save_camera_info

#: The URL an empty ``camera_info_url`` stands for (camera_info_manager's default).
DEFAULT_CAMERA_INFO_URL = "file://${ROS_HOME}/camera_info/${NAME}.yaml"

_NAME = re.compile(r"[A-Za-z0-9_]+")


def check_camera_name(name: str) -> str:
    """Return ``name`` if camera_info_manager accepts it; else raise `FingerpsCalibError`."""
    if not _NAME.fullmatch(name):
        raise FingerpsCalibError(
            f"camera_name {name!r} is not a valid camera name: use only letters, digits and "
            "'_' (it names the calibration file, as in camera_info_manager)")
    return name


def substitute(url: str, camera_name: str, *, environ: Mapping[str, str] | None = None) -> str:
    """``url`` with ``${NAME}`` and ``${ROS_HOME}`` replaced (camera_info_manager's resolveURL).

    Raises
    ------
    FingerpsCalibError
        A ``${...}`` other than these two.
    """
    env = os.environ if environ is None else environ

    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name == "NAME":
            return camera_name
        if name == "ROS_HOME":
            if env.get("ROS_HOME"):
                return env["ROS_HOME"]
            return f"{env.get('HOME', '')}/.ros" if env.get("HOME") else ""
        raise FingerpsCalibError(
            f"camera_info_url {url!r} holds ${{{name}}}: only ${{NAME}} and ${{ROS_HOME}} "
            "are substituted")

    return re.sub(r"\$\{([^}]*)\}", replace, url)


def resolve_camera_info_url(url: str, camera_name: str, *,
                            environ: Mapping[str, str] | None = None) -> Path:
    """The file a camera_info URL names.

    Parameters
    ----------
    url : str
        ``""``, ``file:///...`` or ``package://pkg/...``, with optional substitutions.
    camera_name : str
        Replaces ``${NAME}``.
    environ : mapping, optional
        Environment for ``${ROS_HOME}`` (default ``os.environ``).

    Raises
    ------
    FingerpsCalibError
        An unsupported scheme, a relative ``file://`` path, a package that is not installed.
    """
    resolved = substitute(url or DEFAULT_CAMERA_INFO_URL, camera_name, environ=environ)
    lower = resolved.lower()
    if lower.startswith("file:///"):
        return Path(resolved[len("file://"):])
    if lower.startswith("package://"):
        package, _, rest = resolved[len("package://"):].partition("/")
        if not package or not rest:
            raise FingerpsCalibError(
                f"camera_info_url {url!r} must be package://<package>/<path in its share "
                "directory>")
        from ament_index_python.packages import (  # only for package://
            PackageNotFoundError,
            get_package_share_directory,
        )
        try:
            share = get_package_share_directory(package)
        except PackageNotFoundError:
            raise FingerpsCalibError(
                f"camera_info_url {url!r}: package {package!r} is not installed (not in "
                "AMENT_PREFIX_PATH); source its workspace or use a file:/// URL") from None
        return Path(share) / rest
    if lower.startswith("flash:///"):
        raise FingerpsCalibError(
            f"camera_info_url {url!r}: flash:/// (calibration in the camera's memory) is not "
            "supported by fingerps cameras; use file:/// or package://")
    raise FingerpsCalibError(
        f"camera_info_url {url!r} is not a calibration URL: use file:///absolute/path.yaml, "
        "package://<package>/<path> or leave it empty for "
        f"{DEFAULT_CAMERA_INFO_URL}")


def store_camera_info(path: Path, intrinsics: CameraIntrinsics) -> None:
    """Write ``intrinsics`` to ``path``, atomically and owner-only, making its folders.

    The folders made are owner-only (0700) too; the file is written to a temporary name,
    flushed to disk and renamed (`save_camera_info`), so a reader never sees half a file.

    Raises
    ------
    FingerpsCalibError
        The folder cannot be made or the file cannot be written (the reason is named).
    """
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise FingerpsCalibError(
            f"cannot make the folder {path.parent} for the camera calibration: "
            f"{exc.strerror or exc}; choose a writable camera_info_url") from None
    save_camera_info(path, intrinsics)
