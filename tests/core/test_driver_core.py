"""DriverCore without ROS: opening the hardware, bursts and their bookkeeping, refusals while
the board is away, a board lost mid-burst and found again, camera and board failures, the
simulated rig's changes, closing."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from unittest.mock import Mock

import cv2
import numpy as np
import pytest
from test_board_connection import Timers, said

from fingerps_driver.board.board_connection import BoardSettings, BoardState
from fingerps_driver.board.board_emulator import BoardEmulator, Fault
from fingerps_driver.cameras.camera_setup import (
    FALLBACK_SOURCE,
    CameraBackend,
    CameraSettings,
)
from fingerps_driver.capture.burst import BurstStep
from fingerps_driver.capture.burst_plan import BurstPlan, make_plan
from fingerps_driver.driver_core import DriverCore
from fingerps_driver.errors import BoardDisconnectedError, BoardRejectedError, FingerpsDriverError
from fingerps_driver.simulation import Scene

W, H = 96, 72
PLAN = make_plan(led_count=7, led_order=range(7), exposure_time=0.001, led_level=1.0)


@pytest.fixture(autouse=True)
def _own_ros_home_and_no_threads_left_behind(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    yield
    assert [t for t in threading.enumerate() if t.name == "board-emulator"] == []


class Rig:
    """A DriverCore with the test's logger, timers and record of board changes."""

    def __init__(self, board: BoardSettings, camera: CameraSettings) -> None:
        self.log, self.timers, self.changes = Mock(), Timers(), []
        self.core = DriverCore(board, camera, log=self.log, start_timer=self.timers,
                               on_board_change=lambda: self.changes.append(self.core.board.state))

    def open(self) -> DriverCore:
        self.core.open(node_name="/fingerps/driver", image_topic="/fingerps/image_raw")
        return self.core


@pytest.fixture
def sim():
    rig = Rig(BoardSettings(), CameraSettings(width=W, height=H))
    rig.open()
    yield rig
    rig.core.close()


def _folder(folder: Path) -> str:
    """A DiLiGenT-layout folder of seven grey images, LED i's of value 10 (i + 1)."""
    (folder / "img").mkdir(parents=True)
    names = [f"img/{i:03d}.png" for i in range(7)]
    for i, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), np.full((6, 8), 10 * (i + 1), np.uint8))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    return str(folder)


def test_a_burst_is_captured_and_counted(sim):
    core = sim.core
    assert core.board.state is BoardState.CONNECTED and core.calibration is not None
    assert core.calibration.current.source == FALLBACK_SOURCE
    result = core.capture(PLAN, with_dark=True, repeat_first=True)
    assert result.ok, result.reason
    assert [f.led_index for f in result.frames] == list(range(7))
    assert result.dark is not None and result.repeat is not None
    assert (result.burst_id, core.counters.ok, core.counters.failed) == (1, 1, 0)
    assert core.counters.last_burst_ms == pytest.approx(result.duration_s * 1e3)
    assert list(core.burst_ms) == [core.counters.last_burst_ms]
    core.published(2.5)
    assert (core.counters.last_publish_ms, list(core.publish_ms)) == (2.5, [2.5])
    assert core.capture(PLAN, with_dark=False).burst_id == 2


def test_continuous_capture_counts_towards_the_rate(sim):
    core = sim.core
    core.set_rate(5.0)
    assert core.capture_rate.report(time.monotonic()).requested == 5.0
    core.capture_rate.set_rate(5.0, time.monotonic() - 5.0)  # a full window (5 s) has passed
    assert core.state is BoardState.CONNECTED and core.port == core.board.led_board.port
    for _ in range(3):
        result = core.capture_continuous(PLAN, with_dark=False)
        assert result is not None and result.ok, result
    assert core.capture_rate.report(time.monotonic()).achieved == pytest.approx(3 / 5.0)
    assert core.check_port() is False  # the emulator's pty is there


def test_a_board_lost_mid_burst_is_reported_and_bursts_are_refused_meanwhile(sim):
    core = sim.core
    core.board.emulator.inject(Fault.DISCONNECT, after=3)
    failed = core.capture(PLAN, with_dark=False)
    assert not failed.ok and "BoardDisconnectedError" in failed.reason
    assert failed.reason.startswith("burst 1 failed at step ")
    c = core.counters
    assert (c.failed, c.last_error, c.last_burst_failed) == (1, failed.reason, True)
    sim.log.warning.assert_any_call(failed.reason, throttle_duration_sec=1.0)
    assert core.board.state is BoardState.DISCONNECTED and core.board.disconnects == 1
    assert said(sim.log, "error", f"lost: {failed.reason}; reconnecting with back-off")
    assert sim.changes == [BoardState.DISCONNECTED]
    assert [d for d, _ in sim.timers.started] == [0.5]
    refused = core.capture(PLAN, with_dark=False)
    assert not refused.ok and refused.failed_step is BurstStep.BOARD
    assert refused.error_type is BoardDisconnectedError
    assert core.capture_continuous(PLAN, with_dark=False) is None  # the rate timer waits
    assert refused.burst_id == 0
    assert " is disconnected (" in refused.reason and "; reconnecting, next attempt in" in \
        refused.reason
    assert core.burst_id == 1 and c.failed == 2


def test_a_lost_board_found_again_captures_again(tmp_path):
    link = str(tmp_path / "board")
    with BoardEmulator(7, link_path=link) as emulator:
        rig = Rig(BoardSettings(port=link), CameraSettings(backend=CameraBackend.FOLDER,
                                                           folder=_folder(tmp_path / "set")))
        core = rig.open()
        try:
            assert core.capture(PLAN, with_dark=False).ok
            emulator.inject(Fault.DISCONNECT, after=2)
            assert not core.capture(PLAN, with_dark=False).ok
            assert core.board.state is BoardState.DISCONNECTED
            emulator.reconnect()
            rig.timers.fire()
            assert core.board.state is BoardState.CONNECTED and core.board.reconnects == 1
            assert rig.changes == [BoardState.DISCONNECTED, BoardState.CONNECTED]
            result = core.capture(PLAN, with_dark=False)
            assert result.ok and result.burst_id == 3
            assert [int(f.image[0, 0]) for f in result.frames] == [10, 20, 30, 40, 50, 60, 70]
        finally:
            core.close()


def test_a_board_waited_for_is_said_after_the_camera(tmp_path):
    link = str(tmp_path / "board")
    rig = Rig(BoardSettings(port=link, wait_for_port=True),
              CameraSettings(backend=CameraBackend.FOLDER, folder=_folder(tmp_path / "set")))
    core = rig.open()
    try:
        assert core.state is BoardState.WAITING and core.camera.is_open
        assert core.port == link
        assert [name for name, _, _ in rig.log.method_calls] == ["warning", "warning"]
        assert rig.log.method_calls[0].args[0].startswith("no camera calibration at")
        assert rig.log.method_calls[1].args[0].startswith(f"waiting for the LED board on {link}: ")
        assert rig.timers.started == []
        core.start()
        assert [d for d, _ in rig.timers.started] == [0.5]
        assert "is not there yet" in core.capture(PLAN, with_dark=False).reason
    finally:
        core.close()


def test_a_camera_failure_is_the_camera_s(sim, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("sensor on fire")

    monkeypatch.setattr(sim.core.renderer.rig, "render", broken)
    result = sim.core.capture(PLAN, with_dark=False)
    assert not result.ok and result.camera_failed
    assert sim.core.counters.camera_error == result.reason
    assert sim.core.board.state is BoardState.CONNECTED


def test_a_rejected_command_says_what_to_check(sim):
    result = sim.core.capture(BurstPlan((0, 9), (0.001, 0.001), (1.0, 1.0)), with_dark=False)
    assert not result.ok and result.error_type is BoardRejectedError
    assert said(sim.log, "error", "the board rejected a command: check led_count and "
                                 "led_order against the board")
    assert sim.core.board.state is BoardState.CONNECTED


def test_the_simulated_rig_follows_its_settings(sim):
    core = sim.core
    core.show(Scene.SPHERE)
    assert core.renderer.scene is Scene.SPHERE
    core.move_sphere([0.001, 0.0, 0.09])
    assert core.renderer.rig.config.sphere.center_optical_m == (0.001, 0.0, 0.09)
    core.pose_finger({"roll_deg": 5.0})
    assert core.renderer.rig.config.finger.roll_deg == 5.0
    assert said(sim.log, "info", "sim finger: {'roll_deg': 5.0}")
    core.set_sim_motion([1.0, 0.0], 0)
    assert core.capture(PLAN, with_dark=False).ok


def test_a_camera_that_cannot_be_made_closes_the_board_again():
    rig = Rig(BoardSettings(), CameraSettings(width=W))
    with pytest.raises(FingerpsDriverError, match="set camera_width and camera_height both"):
        rig.open()
    assert rig.core.board.emulator is not None and not rig.core.board.led_board.is_open


def test_a_closed_core_captures_nothing(sim):
    sim.core.close()
    sim.core.close()  # idempotent
    assert not sim.core.camera.is_open and not sim.core.board.led_board.is_open
    with pytest.raises(FingerpsDriverError, match="the driver is shutting down"):
        sim.core.capture(PLAN, with_dark=False)
