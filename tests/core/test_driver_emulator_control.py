"""The board emulator's control channel (UNIX socket) and its deferred power cut.

In process: EmulatorControlServer + BoardEmulatorControl around a BoardEmulator on a pty,
with LedBoard and capture_burst on the serial side. One test runs the console script
``board_emulator --control`` as a separate process.
"""

import os
import signal
import time

import numpy as np
import pytest
from led_history import masks_lit_since, repeats_since
from polling import poll_until

from fingerps_driver.board.board_emulator import Fault
from fingerps_driver.board.emulator_control import EmulatorControlServer
from fingerps_driver.board.emulator_control_client import BoardEmulatorControl
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import SimulatedCamera
from fingerps_driver.capture.burst import BurstStep, capture_burst
from fingerps_driver.errors import (
    BoardDisconnectedError,
    BoardEmulatorError,
    BoardNotFoundError,
    CameraError,
)

LEDS = tuple(range(7))
pytestmark = pytest.mark.usefixtures("no_emulator_threads_left")


@pytest.fixture
def control(emulator, tmp_path):
    path = str(tmp_path / "control")
    with EmulatorControlServer(emulator, path), BoardEmulatorControl(path) as client:
        yield client


@pytest.fixture
def board(emulator):
    with LedBoard(emulator.port, timeout_s=0.05, retries=2) as client:
        yield client


def _camera(lit_leds):
    """A camera whose every pixel is the mask of the LEDs it sees lit."""
    camera = SimulatedCamera(lambda lit: np.full((4, 5), sum(1 << i for i in lit), np.uint16),
                             lit_leds, width=5, height=4, encoding="mono16")
    camera.open()
    return camera


def _burst(board, camera, burst_id=1):
    return capture_burst(board, camera, burst_id=burst_id, led_order=LEDS, exposures_s=0.01,
                         levels=1.0)


def test_state_lit_and_history_follow_the_serial_switches(control, board, emulator):
    assert control.ping()
    assert control.lit_mask() == 0
    before = time.monotonic()
    board.set_leds(1 << 3)
    assert control.lit_mask() == 1 << 3 and control.lit_leds() == (3,)
    board.set_level(1, 40)
    state = control.state()
    assert state["mask"] == 8 and state["lit"] == [3] and state["connected"]
    assert state["levels"][1] == 40 and state["port"] == emulator.port
    board.all_off()
    after = time.monotonic()
    history = control.history()
    assert [mask for _, mask in history] == [8, 0]
    # monotonic time is system-wide: the switches' times fall between this process's clock
    # readings around them, in order
    (lit_at, _), (off_at, _) = history
    assert before <= lit_at <= off_at <= after
    assert control.history(1) == history[-1:]


def test_faults_injected_through_the_channel_are_recovered_by_the_client(control, board):
    assert control.inject(Fault.DROP_REPLY, 2) == ["DROP_REPLY", "DROP_REPLY"]
    assert board.set_leds(1) == 1
    assert board.resends == 2
    control.inject("corrupt_byte")
    assert board.set_leds(2) == 2
    assert board.resends == 3
    control.inject("slow_reply", 3)
    control.clear_faults()
    assert control.state()["pending_faults"] == []


def test_deferred_power_cut_fails_the_burst_at_the_known_step(control, board, emulator):
    camera = _camera(control.lit_leds)
    start, resends = time.monotonic(), board.resends
    assert _burst(board, camera).ok
    # a burst sends 7 LEVEL, then LEDS per LED, then OFF: the 10th reply is LED 2's switch
    control.inject(Fault.DISCONNECT, after=9)
    result = _burst(board, camera, burst_id=2)
    assert not result.ok and result.failed_step is BurstStep.SWITCH
    assert result.error_type is BoardDisconnectedError, result.reason
    assert "LED 2" in result.reason
    assert not board.is_open and board.acknowledged_mask is None
    poll_until(lambda: not control.state()["connected"], 2, interval_s=0.01)
    assert not control.state()["connected"] and not os.path.exists(emulator.port)
    # the request was executed, then the board lost power
    masks = masks_lit_since(control.history(), start)
    assert masks == [1 << i for i in LEDS] + [0] + [1, 2, 4, 0]
    assert repeats_since(control.history(), start) <= board.resends - resends
    with pytest.raises(BoardNotFoundError):
        board.open()

    control.reconnect()
    board.open()
    start, resends = time.monotonic(), board.resends
    result = _burst(board, camera, burst_id=3)
    assert result.ok, result.reason
    assert [int(f.image[0, 0]) for f in result.frames] == [1 << f.led_index
                                                            for f in result.frames]
    assert masks_lit_since(control.history(), start) == [1 << i for i in LEDS] + [0]
    assert repeats_since(control.history(), start) <= board.resends - resends


def test_immediate_disconnect_and_errors_are_answered(control, board, tmp_path):
    control.disconnect()
    with pytest.raises(BoardDisconnectedError):
        board.set_leds(1)
    with pytest.raises(BoardEmulatorError, match="unknown command"):
        control.command("explode")
    with pytest.raises(BoardEmulatorError, match="unknown fault"):
        control.inject("fire")
    with pytest.raises(BoardEmulatorError, match="usage"):
        control.command("inject drop_reply 1 2")
    with pytest.raises(BoardEmulatorError, match="count must be"):
        control.inject(Fault.DROP_REPLY, 0)
    # A huge count is refused with a reason (nothing of its size is allocated) and the
    # channel keeps answering.
    with pytest.raises(BoardEmulatorError, match="count \\+ after must be <= 10000"):
        control.command("inject drop_reply 100000000000")
    with pytest.raises(BoardEmulatorError, match="after must be"):
        control.command("inject drop_reply 1 after 100000000000")
    assert control.command("ping") is True
    assert "inject FAULT [COUNT] [after N]" in control.command("help")
    control.reconnect()
    assert board.is_open is False
    board.open()
    assert board.set_leds(4) == 4


def test_clients_reconnect_and_bad_paths_are_refused(emulator, tmp_path):
    path = str(tmp_path / "control")
    with pytest.raises(BoardEmulatorError, match="cannot reach"):
        BoardEmulatorControl(path).ping()
    regular = tmp_path / "regular"
    regular.write_text("keep")
    with pytest.raises(BoardEmulatorError, match="not a socket"):
        EmulatorControlServer(emulator, str(regular)).start()
    assert regular.read_text() == "keep"
    client = BoardEmulatorControl(path)
    second = BoardEmulatorControl(path)
    server = EmulatorControlServer(emulator, path)
    server.start()
    assert client.ping() and second.ping()
    server.stop()
    server.stop()
    assert not os.path.exists(path)
    server = EmulatorControlServer(emulator, path)  # a restarted emulator: clients reconnect
    server.start()
    try:
        assert client.lit_mask() == 0 and second.ping()
    finally:
        client.close()
        second.close()
        server.stop()


def test_a_camera_that_cannot_see_the_board_gives_no_frame(tmp_path):
    camera = _camera(BoardEmulatorControl(str(tmp_path / "nowhere")).lit_leds)
    with pytest.raises(CameraError, match="cannot see which LEDs are lit"):
        camera.grab(timeout_s=0.1)


def test_console_script_serves_the_control_channel(tmp_path, emulator_script):
    link, path = tmp_path / "board", tmp_path / "control"
    process = emulator_script("--link", str(link), "--control", str(path))
    assert f"control {path}" in process.stdout.readline()
    with LedBoard(str(link)) as board, BoardEmulatorControl(str(path)) as control:
        board.set_leds(1 << 5)
        assert control.lit_leds() == (5,)
        control.inject(Fault.DROP_REPLY)
        assert board.set_leds(1 << 6) == 1 << 6 and board.resends == 1
        control.disconnect()
        assert not link.exists()
        control.reconnect()
        assert link.exists()
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=5) == 0
    assert not link.exists() and not path.exists()
