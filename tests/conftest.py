"""Fixtures shared by the core and the graph tests.

- ``ros_domain``: a ROS_DOMAIN_ID of the test's own (40-101, held with a lock file so that
  concurrent test runs and benchmarks on this machine never share one),
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a ``ROS_HOME`` of the test's own (so no
  camera calibration in the user's ``~/.ros/camera_info`` reaches a test's driver, and none
  a test stores reaches the user), set in ``os.environ`` so child processes and this
  process's rclpy all use them.
- ``ros_node``: an rclpy node of the test process (``/fingerps_test``) in a context of its own
  in that domain (initialised without signal handlers), destroyed at teardown.
- ``installed(package, name)``: the path of an installed executable (``make build``).
- ``restore_umask``: the process's umask put back after the test (which may change it).
- ``rig``, ``finger_images``: the default simulated rig and its finger under each LED.
- ``emulator``: a 7-LED board emulator on a pseudo-terminal; ``emulator_threads()`` its live
  threads, and ``no_emulator_threads_left`` (for ``pytest.mark.usefixtures``) fails a test
  that leaves one running.
- ``emulator_script(*args)``: the emulator's console script in a process of its own
  (``python -m fingerps_driver.board.board_emulator``; ``module=`` another one, e.g. the
  firmware simulator's), killed at teardown if still running.
- ``firmware_board``: the board's real firmware under simavr (``FirmwareSim``) on a
  pseudo-terminal linked at ``tmp_path / "firmware_board"``; ``traced_firmware_board`` the
  same tracing its pins and UART to ``tmp_path / "board.vcd"`` (complete once stopped). A
  firmware that is not built fails the test with the message to run ``make firmware``
  (never skipped).
- ``board_port``: parametrised over the two boards, ``emulator`` and ``firmware``: a
  ``BoardPort`` (kind, port, INFO's firmware token and the emulator or the simulator), so
  that one suite runs against both.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
from ros_domain import domain_env, own_ros_domain

if TYPE_CHECKING:
    from rclpy.node import Node

    from fingerps_driver.board.board_emulator import BoardEmulator
    from fingerps_driver.board.firmware_sim import FirmwareSim
    from fingerps_driver.simulation import SimulatedRig

INSTALL = Path(__file__).resolve().parents[1] / "install"


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[int]:
    """A ROS domain of this test's own (``ros_domain.own_ros_domain``), on localhost only;
    returns its id."""
    with ExitStack() as stack:
        try:
            domain_id = stack.enter_context(own_ros_domain())
        except RuntimeError as exc:
            pytest.fail(str(exc))
        for name, value in domain_env(domain_id, ROS_HOME=str(tmp_path / "ros_home")).items():
            if os.environ.get(name) != value:
                monkeypatch.setenv(name, value)
        for name in ("ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY"):
            monkeypatch.delenv(name, raising=False)
        yield domain_id



@pytest.fixture
def ros_node(ros_domain: int) -> Iterator[Node]:
    """A node of the test process (``/fingerps_test``) in the test's ROS domain."""
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain,
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("fingerps_test", context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture(scope="session")
def installed() -> Callable[[str, str], Path]:
    """``installed(package, name)``: ``install/<package>/lib/<package>/<name>``; fails the
    test if it is not built."""
    def path(package: str, name: str) -> Path:
        exe = INSTALL / package / "lib" / package / name
        if not os.access(exe, os.X_OK):
            pytest.fail(f"{exe} is not built: run 'make build' (then 'source tools/ros_env.sh')")
        return exe
    return path


@pytest.fixture
def restore_umask() -> Iterator[None]:
    """The process's umask as before the test, whatever the test set."""
    saved = os.umask(0o022)
    os.umask(saved)
    yield
    os.umask(saved)


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    """The default simulated rig (``SimulatedRig()``)."""
    from fingerps_driver.simulation import SimulatedRig
    return SimulatedRig()


@pytest.fixture(scope="module")
def finger_images(rig: SimulatedRig) -> np.ndarray:
    """(K, H, W) uint8: the rig's finger under LED k alone, noise seeded with 30 + k."""
    from fingerps_driver.simulation import Scene
    return rig.render_burst(Scene.FINGER, seed=30)


def _emulator_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("board-emulator")]


@pytest.fixture
def emulator_threads() -> Callable[[], list[threading.Thread]]:
    """``emulator_threads()``: the board emulators' live threads (named ``board-emulator*``)."""
    return _emulator_threads


@pytest.fixture
def no_emulator_threads_left() -> Iterator[None]:
    """Fails the test if a board emulator's thread still runs after it."""
    yield
    assert _emulator_threads() == []


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[BoardEmulator]:
    """A 7-LED ``BoardEmulator`` on a pseudo-terminal linked at ``tmp_path / "board"``."""
    from fingerps_driver.board.board_emulator import BoardEmulator
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emu:
        yield emu


@pytest.fixture
def emulator_script() -> Iterator[Callable[..., subprocess.Popen]]:
    """``emulator_script(*args)`` starts ``python -m fingerps_driver.board.board_emulator
    *args`` with this process's ``sys.path``, its stdout a text pipe; a process still running at
    teardown is killed. Keywords: ``module`` another module of the package (e.g.
    ``board.firmware_sim``), ``env`` extra environment variables, ``stderr=True`` its
    stderr a text pipe too."""
    started: list[subprocess.Popen] = []

    def start(*args: str, module: str = "board.board_emulator",
              env: dict[str, str] | None = None, stderr: bool = False) -> subprocess.Popen:
        environment = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), **(env or {})}
        process = subprocess.Popen(
            [sys.executable, "-m", f"fingerps_driver.{module}", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE if stderr else None, text=True,
            env=environment)
        started.append(process)
        return process

    yield start
    for process in started:
        if process.poll() is None:
            process.kill()
            process.wait()
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()


def _firmware_sim(link: Path, vcd: Path | None) -> Iterator[FirmwareSim]:
    from fingerps_driver.board.firmware_sim import FirmwareSim
    from fingerps_driver.errors import FirmwareNotBuiltError
    sim = FirmwareSim(str(link), vcd=None if vcd is None else str(vcd))
    try:
        sim.start()
    except FirmwareNotBuiltError as exc:
        pytest.fail(str(exc))
    try:
        yield sim
    finally:
        sim.stop()


@pytest.fixture
def firmware_board(tmp_path: Path) -> Iterator[FirmwareSim]:
    """The board's firmware under simavr on a pty linked at ``tmp_path / "firmware_board"``;
    stopped (SIGTERM) at teardown."""
    yield from _firmware_sim(tmp_path / "firmware_board", None)


@pytest.fixture
def traced_firmware_board(tmp_path: Path) -> Iterator[FirmwareSim]:
    """``firmware_board`` tracing its pins and UART bytes to ``tmp_path / "board.vcd"``
    (complete once stopped). Not for long runs with LEDs at levels 1..254: every PWM edge
    is a line of the trace."""
    yield from _firmware_sim(tmp_path / "firmware_board", tmp_path / "board.vcd")


@dataclass(frozen=True)
class BoardPort:
    """One of the two boards the board tests run against."""

    kind: str
    """``emulator`` (``BoardEmulator``) or ``firmware`` (the AVR firmware under simavr)."""
    port: str
    firmware: str
    """What it answers ``INFO`` (with 7 LEDs)."""
    emulator: BoardEmulator | None = None
    sim: FirmwareSim | None = None


@pytest.fixture(params=["emulator", "firmware"])
def board_port(request: pytest.FixtureRequest) -> BoardPort:
    """The emulator's or the firmware's pty (7 LEDs each)."""
    if request.param == "emulator":
        from fingerps_driver.board.board_emulator import FIRMWARE
        emulator = request.getfixturevalue("emulator")
        return BoardPort("emulator", emulator.port, FIRMWARE, emulator=emulator)
    from fingerps_driver.board.firmware_sim import FIRMWARE_NAME
    sim = request.getfixturevalue("firmware_board")
    return BoardPort("firmware", sim.port, FIRMWARE_NAME, sim=sim)
