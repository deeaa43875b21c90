"""Keeping a bags directory under a size limit: the oldest whole sessions are removed first.

A kiosk records every session into one ``bags_dir``; without a limit the disk fills. Here a
session is a sub-directory of ``bags_dir`` that holds a rosbag2 bag (a ``metadata.yaml`` or
an ``.mcap`` file at its top level); nothing else in ``bags_dir`` is counted or touched. Its
age is the time its newest file was last written. `enforce_limit` removes whole sessions,
oldest first, until the sessions add up to at most the limit, and never the session being
recorded (it may be larger than the limit on its own: the recorder then says so).

No rclpy here.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from fingerps_recon.sessions.bag_metadata import METADATA_FILENAME


@dataclass(frozen=True)
class StoredSession:
    """A session bag in the bags directory.

    Attributes
    ----------
    path : Path
        Its directory.
    size_bytes : int
        Bytes of the files in it (recursively).
    last_written_ns : int
        Latest modification time of its files, ns since the epoch.
    """

    path: Path
    size_bytes: int
    last_written_ns: int


@dataclass(frozen=True)
class RetentionResult:
    """What `enforce_limit` did.

    Attributes
    ----------
    removed : tuple[StoredSession, ...]
        Sessions removed, oldest first.
    total_bytes : int
        Bytes of the sessions left (the one being recorded included).
    failed : tuple[str, ...]
        Sessions that could not be removed, with the reason.
    """

    removed: tuple[StoredSession, ...] = ()
    total_bytes: int = 0
    failed: tuple[str, ...] = ()


def _files_of(directory: Path) -> tuple[int, int]:
    """Total bytes and latest mtime (ns) of the files under ``directory``."""
    size, latest = 0, 0
    for root, _dirs, files in os.walk(directory):
        for name in files:
            try:
                info = os.stat(os.path.join(root, name))
            except OSError:  # removed meanwhile
                continue
            size += info.st_size
            latest = max(latest, info.st_mtime_ns)
    return size, latest


def _is_bag(directory: Path) -> bool:
    try:
        return any(entry.is_file() and (entry.name == METADATA_FILENAME
                                        or entry.name.endswith(".mcap"))
                   for entry in os.scandir(directory))
    except OSError:
        return False


def stored_sessions(bags_dir: str | os.PathLike[str]) -> list[StoredSession]:
    """The session bags in ``bags_dir``, oldest first ([] when it does not exist)."""
    root = Path(bags_dir)
    try:
        entries = [Path(e.path) for e in os.scandir(root) if e.is_dir(follow_symlinks=False)]
    except OSError:
        return []
    sessions = []
    for directory in entries:
        if _is_bag(directory):
            size, latest = _files_of(directory)
            sessions.append(StoredSession(directory, size, latest))
    sessions.sort(key=lambda s: (s.last_written_ns, s.path.name))
    return sessions


def enforce_limit(bags_dir: str | os.PathLike[str], limit_bytes: int, *,
                  keep: str | os.PathLike[str] | None = None) -> RetentionResult:
    """Remove the oldest sessions of ``bags_dir`` until its sessions total ``limit_bytes``.

    Parameters
    ----------
    bags_dir : str or os.PathLike
        The bags directory.
    limit_bytes : int
        The most the sessions may add up to; 0 or less: no limit (nothing is removed).
    keep : str or os.PathLike, optional
        A session never removed (the one being recorded).

    Returns
    -------
    RetentionResult
        The sessions removed and the bytes left.
    """
    sessions = stored_sessions(bags_dir)
    total = sum(s.size_bytes for s in sessions)
    if limit_bytes <= 0 or total <= limit_bytes:
        return RetentionResult(total_bytes=total)
    kept = Path(keep).resolve() if keep is not None else None
    removed, failed = [], []
    for session in sessions:
        if total <= limit_bytes:
            break
        if kept is not None and session.path.resolve() == kept:
            continue
        try:
            shutil.rmtree(session.path)
        except OSError as err:
            failed.append(f"{session.path}: {err.strerror or err}")
            continue
        removed.append(session)
        total -= session.size_bytes
    return RetentionResult(removed=tuple(removed), total_bytes=total, failed=tuple(failed))
