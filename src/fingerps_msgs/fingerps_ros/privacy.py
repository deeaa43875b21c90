"""Private by default: what fingerps writes and offers holds fingerprints (biometric data).

- Files and directories: every node (:func:`fingerps_ros.node_runner.run_node`) and every
  command-line tool sets the process umask to 077 before it writes anything, so bags,
  metadata, calibrations, images, clouds and logs it creates are owner-only (0600/0700),
  and so are the shared-memory segments Fast DDS creates in /dev/shm for its messages
  (raw finger images among them). ``FINGERPS_UMASK`` (octal, e.g. ``027`` to let the
  owner's group read) relaxes it; ``keep`` leaves the user's umask alone.
- Discovery: what the project starts (demo, bringup, the launch file, ``tools/ros_env.sh``)
  talks to this machine only (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) unless the user
  has set ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (e.g. ``SUBNET`` to open the graph to the
  network deliberately).
"""

from __future__ import annotations

import os

from fingerps_ros.errors import PrivacySettingError

UMASK_VARIABLE = "FINGERPS_UMASK"
DEFAULT_UMASK = 0o077
DISCOVERY_VARIABLE = "ROS_AUTOMATIC_DISCOVERY_RANGE"


def apply_private_umask() -> int | None:
    """Set the process umask from ``FINGERPS_UMASK`` (default 077); return the umask set, or
    None when the variable says ``keep``. Raises PrivacySettingError on a bad value."""
    text = os.environ.get(UMASK_VARIABLE, "").strip()
    if text.lower() == "keep":
        return None
    try:
        mask = int(text, 8) if text else DEFAULT_UMASK
    except ValueError:
        mask = -1
    if not 0 <= mask <= 0o777:
        raise PrivacySettingError(
            f"{UMASK_VARIABLE}={text!r} is not an octal umask: use e.g. 077 (owner only, the "
            "default), 027 (group may read) or keep (the user's umask)")
    os.umask(mask)
    return mask


def use_localhost_discovery() -> str:
    """Make processes started from here discover on this machine only, unless the user
    chose a discovery range; return the range in force."""
    return os.environ.setdefault(DISCOVERY_VARIABLE, "LOCALHOST")


def start_private_tool(prog: str) -> bool:
    """:func:`apply_private_umask` for a command-line tool's ``main``: False, after one line
    on stderr naming the problem, if ``FINGERPS_UMASK`` is bad (the tool then exits 2)."""
    try:
        apply_private_umask()
    except PrivacySettingError as exc:
        import sys

        print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
        return False
    return True
