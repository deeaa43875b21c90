"""fingerps_ros.privacy: owner-only files by default, localhost discovery by default."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fingerps_ros.errors import PrivacySettingError
from fingerps_ros.privacy import apply_private_umask, start_private_tool, use_localhost_discovery


@pytest.mark.parametrize(("value", "expected"), [("", 0o077), ("027", 0o027), ("0", 0)])
def test_the_umask_is_owner_only_unless_relaxed(restore_umask, monkeypatch, tmp_path: Path,
                                                value: str, expected: int) -> None:
    monkeypatch.setenv("FINGERPS_UMASK", value)
    assert apply_private_umask() == expected
    path = tmp_path / "file"
    path.write_bytes(b"finger")
    assert path.stat().st_mode & 0o777 == 0o666 & ~expected


def test_keep_leaves_the_users_umask(restore_umask, monkeypatch) -> None:
    os.umask(0o002)
    monkeypatch.setenv("FINGERPS_UMASK", "keep")
    assert apply_private_umask() is None
    assert os.umask(0o002) == 0o002


@pytest.mark.parametrize("value", ["abc", "999", "-1", "1000"])
def test_a_bad_umask_is_refused_with_what_to_use(restore_umask, monkeypatch, capsys,
                                                 value: str) -> None:
    monkeypatch.setenv("FINGERPS_UMASK", value)
    with pytest.raises(PrivacySettingError, match=r"use e\.g\. 077"):
        apply_private_umask()
    assert start_private_tool("tool") is False
    assert "tool: error: FINGERPS_UMASK=" in capsys.readouterr().err


def test_discovery_is_localhost_unless_the_user_chose(monkeypatch) -> None:
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    assert use_localhost_discovery() == "LOCALHOST"
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    assert use_localhost_discovery() == "SUBNET"
