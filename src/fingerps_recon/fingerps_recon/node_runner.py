"""The one ``main`` of every fingerps node: init, spin, clean shutdown, one-line errors.

A node whose construction fails on bad input (a missing file, a bad parameter value, a
serial port that cannot be opened) ends with one line naming the problem and the fix, and
exit code 2 - no traceback. Ctrl-C (SIGINT) and SIGTERM both end the spin and run
``destroy_node()``, which closes the node's resources.

With Fast DDS (the default RMW) and no profile of the user's (``FASTRTPS_DEFAULT_PROFILES_FILE``
unset), every node uses ``fingerps_recon``'s ``config/fastdds_large_data.xml``: a shared-memory
segment large enough for a burst's messages and a short heartbeat, without which a loaded
machine delivered reconstructions seconds late (the file says why).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from fingerps_recon.parameters import UnknownParameterError

EXIT_BAD_INPUT = 2
PROFILES_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
PROFILE_FILE = "fastdds_large_data.xml"

_PARAMETER_ERRORS = (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)


class StartupError(Exception):
    """A node cannot start; the message names the problem and what to do."""


def run_node(
    make_node: Callable[[], Node],
    *,
    args: list[str] | None = None,
    name: str = "fingerps",
    executor: Callable[[], Executor] = SingleThreadedExecutor,
    expected_errors: tuple[type[Exception], ...] = (),
) -> int:
    """Construct a node with ``make_node`` and spin it until shutdown; return an exit code.

    ``expected_errors`` (besides ``StartupError``) raised by construction are reported as
    one line on stderr and give exit code 2.
    """
    use_large_data_profile()
    try:
        rclpy.init(args=args)
    except RCLError as exc:
        reason = str(exc).split(", at ")[0]
        print(f"[{name}] error: {reason}. Check the --ros-args and the parameter file.",
              file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    node: Node | None = None
    try:
        node = make_node()
        spinner = executor()
        spinner.add_node(node)
        spinner.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (StartupError, UnknownParameterError, *_PARAMETER_ERRORS, *expected_errors) as exc:
        print(f"[{name}] error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def use_large_data_profile() -> str | None:
    """Point Fast DDS at ``config/fastdds_large_data.xml`` of this package, unless another RMW
    is chosen or the user set a profile file; returns the file used, or None. Call before
    ``rclpy.init()`` (Fast DDS reads the variable when the context starts)."""
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    if os.environ.get(PROFILES_VARIABLE):
        return None
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        path = Path(get_package_share_directory("fingerps_recon")) / "config" / PROFILE_FILE
    except (ImportError, PackageNotFoundError, ValueError):
        return None
    if not path.is_file():
        return None
    os.environ[PROFILES_VARIABLE] = str(path)
    return str(path)
