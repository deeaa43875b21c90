"""Fixtures shared by the core and the graph tests.

- ``ros_domain``: a ROS_DOMAIN_ID of the test's own (40-101, held with a lock file so that
  concurrent test runs and benchmarks on this machine never share one),
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a ``ROS_HOME`` of the test's own (so no
  camera calibration in the user's ``~/.ros/camera_info`` reaches a test's driver, and none
  a test stores reaches the user), set in ``os.environ`` so child processes and this
  process's rclpy all use them.
"""

from __future__ import annotations

import fcntl
import random
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

DOMAIN_RANGE = range(40, 102)  # Fast DDS ports of ids above 101 can collide with ephemeral ports


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[int]:
    """A ROS domain of this test's own, on localhost only; returns its id."""
    lock_dir = Path(tempfile.gettempdir()) / "fingerps_ros_domains"
    lock_dir.mkdir(exist_ok=True)
    candidates = list(DOMAIN_RANGE)
    random.shuffle(candidates)
    for domain_id in candidates:
        handle = open(lock_dir / f"{domain_id}.lock", "w")  # held until teardown
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        break
    else:
        pytest.fail(f"every ROS domain id in {DOMAIN_RANGE} is held by another test run")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    try:
        yield domain_id
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()
