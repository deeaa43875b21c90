"""The one ``main`` of every fingerps node: init, spin, clean shutdown, one-line errors.

A node whose construction fails on bad input (a missing file, a bad parameter value, a
serial port that cannot be opened) ends with one line naming the problem and the fix, and
exit code 2 - no traceback. Ctrl-C (SIGINT) and SIGTERM both end the spin and run
``destroy_node()``, which closes the node's resources.

Stopping is idempotent and signal-safe. ``ros2 launch`` run non-interactively forwards SIGINT
to each node and the process group gets one too, so a node often sees two signals (and a
supervisor may follow with SIGTERM). rclpy (Jazzy) installs C handlers for SIGINT and SIGTERM
that shut the context down (ending the spin) and then chain to the handler that was there
before ``rclpy.init()``: for SIGINT that is Python's, which raises KeyboardInterrupt - at
every signal, also inside ``destroy_node()`` (the recorder finishing its bag). So
``run_node`` installs its own Python handler for both signals before ``rclpy.init()`` (rclpy
chains to it). A signal while the node is being made raises KeyboardInterrupt once, which
ends start-up quietly. While spinning, the first signal is only noted: no KeyboardInterrupt
lands inside a callback (one was seen swallowed there, leaving the spin to rclpy's context
shutdown, which can race the executor into an RCLError "context is not valid"); the spin
runs in slices of ``SPIN_SLICE_S`` and ends at the next wake-up (rclpy's handler wakes the
executor at once), an RCLError of a context shut down by the signal counts as the stop.
Every further SIGINT/SIGTERM is ignored (one line on stderr) while ``destroy_node()`` closes
the resources, and afterwards both signals stay ignored until the process exits, with 0.

With Fast DDS (the default RMW) and no profile of the user's (``FASTRTPS_DEFAULT_PROFILES_FILE``
unset), every node uses ``fingerps_recon``'s ``config/fastdds_large_data.xml``: a shared-memory
segment large enough for a burst's messages and a short heartbeat, without which a loaded
machine delivered reconstructions seconds late (the file says why).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
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

from fingerps_ros.command_line import EXIT_BAD_INPUT
from fingerps_ros.errors import PrivacySettingError
from fingerps_ros.parameters import UnknownParameterError
from fingerps_ros.privacy import apply_private_umask

PROFILES_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"
PROFILE_FILE = "fastdds_large_data.xml"

_PARAMETER_ERRORS = (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
)


class StartupError(Exception):
    """A node cannot start; the message names the problem and what to do."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
EXIT_GRACE_S = 5.0  # after the node's resources are closed, the interpreter's exit at most
SPIN_SLICE_S = 0.5


class StopSignals:
    """The Python handler of SIGINT and SIGTERM for a node's whole life (see the module doc).

    Phases: ``starting`` (the first signal raises KeyboardInterrupt: start-up is
    abandoned), ``spinning`` (the first signal is only noted in ``received``; the spin loop
    ends on it) and ``stopping`` (every signal is ignored, with one line on stderr; so is
    every signal after the first in any phase). The handler never prints through
    ``sys.stderr`` (a signal can arrive while the main thread writes to it, and a buffered
    write then raises "reentrant call"): it writes to fd 2 directly.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.phase = "starting"
        self.received: list[int] = []

    def install(self) -> None:
        for signum in STOP_SIGNALS:
            signal.signal(signum, self._handle)

    def _handle(self, signum: int, _frame: object) -> None:
        self.received.append(signum)
        if self.phase == "stopping" or len(self.received) > 1:
            _write_stderr(f"[{self.name}] {signal.Signals(signum).name} received while "
                          "stopping: ignored until the node's resources are closed\n")
            return
        if self.phase == "starting":
            self.phase = "stopping"
            raise KeyboardInterrupt

    def stopping(self) -> None:
        """From now on every SIGINT/SIGTERM is ignored."""
        self.phase = "stopping"

    def ignore_until_exit(self) -> None:
        """Resources closed: ignore both signals at the OS level until the process exits (a
        Python handler would be reset to the default at interpreter exit, and a late signal
        would then kill the process with -2 instead of its exit code)."""
        for signum in STOP_SIGNALS:
            signal.signal(signum, signal.SIG_IGN)


def _exit_anyway_after(seconds: float, code: int) -> None:
    """The node's resources are closed: if the interpreter has not exited ``seconds`` later
    (a thread of the executor's pool, say, stuck in a library call), end the process with
    ``code`` all the same, so a stop never hangs. A daemon thread: a normal exit ends it."""
    def exit_now() -> None:
        time.sleep(seconds)
        _write_stderr(f"process still running {seconds:g} s after its node stopped: exiting\n")
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)

    threading.Thread(target=exit_now, name="exit_anyway", daemon=True).start()


def _write_stderr(text: str) -> None:
    try:
        os.write(2, text.encode())
    except OSError:
        pass


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
    signals = StopSignals(name)
    signals.install()
    code = 1  # an exception nobody expected ends the process with 1
    try:
        code = _run(make_node, signals, args=args, name=name, executor=executor,
                    expected_errors=expected_errors)
        return code
    except KeyboardInterrupt:  # a signal while starting, before a node existed
        code = 0
        return code
    finally:
        signals.stopping()
        signals.ignore_until_exit()
        _exit_anyway_after(EXIT_GRACE_S, code)


def _run(
    make_node: Callable[[], Node],
    signals: StopSignals,
    *,
    args: list[str] | None,
    name: str,
    executor: Callable[[], Executor],
    expected_errors: tuple[type[Exception], ...],
) -> int:
    try:
        apply_private_umask()  # files and shared-memory segments owner-only (privacy.py)
    except PrivacySettingError as exc:
        print(f"[{name}] error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
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
        signals.phase = "spinning"
        _spin(spinner, signals)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (StartupError, UnknownParameterError, *_PARAMETER_ERRORS, *expected_errors) as exc:
        signals.stopping()
        print(f"[{name}] error: {exc}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    finally:
        signals.stopping()  # before anything is closed: no signal interrupts the closing
        try:
            if node is not None:
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
    return 0


def _spin(spinner: Executor, signals: StopSignals) -> None:
    """Spin until a stop signal or the context's shutdown (see the module doc)."""
    context = spinner.context
    while context.ok() and not signals.received:
        try:
            spinner.spin_once(timeout_sec=SPIN_SLICE_S)
        except RCLError:
            if signals.received or not context.ok():
                return  # the signal's context shutdown raced the executor's wait set
            raise


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
