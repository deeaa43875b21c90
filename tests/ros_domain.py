"""A ROS domain of one's own, for the graph tests (the ``ros_domain`` fixture of
tests/conftest.py) and the benchmarks (bench/ puts this folder on its path): an id that no
concurrent test or benchmark on this machine holds (a lock file each), and the environment
of a process in it (``domain_env``)."""

from __future__ import annotations

import fcntl
import os
import random
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

DOMAIN_RANGE = range(40, 102)  # Fast DDS ports of ids above 101 can collide with ephemeral ports


@contextmanager
def own_ros_domain() -> Iterator[int]:
    """Hold a free ROS_DOMAIN_ID for the block; RuntimeError if every one is held."""
    lock_dir = Path(tempfile.gettempdir()) / "fingerps_ros_domains"
    lock_dir.mkdir(exist_ok=True)
    candidates = list(DOMAIN_RANGE)
    random.shuffle(candidates)
    for domain_id in candidates:
        handle = open(lock_dir / f"{domain_id}.lock", "w")  # held until the block ends
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        try:
            yield domain_id
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
            handle.close()
        return
    raise RuntimeError(f"every ROS domain id in {DOMAIN_RANGE} is held by another run")


def domain_env(domain_id: int, **extra: str) -> dict[str, str]:
    """``os.environ`` for a process in the ROS domain ``domain_id`` on this host only:
    ``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, without
    ``ROS_STATIC_PEERS`` and ``ROS_LOCALHOST_ONLY`` (as the tests' ``ros_domain``), then
    ``extra``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY")}
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", **extra)
    return env
