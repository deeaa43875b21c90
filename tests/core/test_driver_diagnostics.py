"""The driver's /diagnostics statuses from a DriverCore's state, without a node: keys in the
order the README lists them, levels and messages of a healthy, a lost and a waiting board,
a camera that failed, continuous capture falling behind."""

from __future__ import annotations

import time
from unittest.mock import Mock

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from test_board_connection import Timers

from fingerps_driver.board.board_connection import BoardSettings, BoardState
from fingerps_driver.cameras.camera_setup import CameraSettings
from fingerps_driver.capture.burst_plan import make_plan
from fingerps_driver.driver_core import DriverCore
from fingerps_driver.driver_diagnostics import driver_statuses

PLAN = make_plan(led_count=7, led_order=range(7), exposure_time=0.001, led_level=1.0)


@pytest.fixture
def core(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    core = DriverCore(BoardSettings(), CameraSettings(width=96, height=72), log=Mock(),
                      start_timer=Timers())
    core.open(node_name="/fingerps/driver", image_topic="/fingerps/image_raw")
    yield core
    core.close()


def _values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_a_healthy_driver(core):
    assert core.capture(PLAN, with_dark=False).ok
    core.published(1.25)
    board, camera, bursts = driver_statuses("driver", core, compressed_failures=2)
    port = core.board.led_board.port
    assert (board.name, board.hardware_id, board.level) == ("driver: board", port,
                                                           DiagnosticStatus.OK)
    assert board.message == "connected (fingerps-emu-1.0)"
    assert _values(board) == {
        "state": "connected", "port": port, "firmware": "fingerps-emu-1.0", "resends": "0",
        "disconnects": "0", "reconnects": "0", "reconnect_attempts": "0",
        "last_board_error": ""}
    assert (camera.name, camera.hardware_id, camera.level, camera.message) == (
        "driver: camera", "sim", DiagnosticStatus.OK, "ok")
    assert _values(camera) == {
        "backend": "sim", "device": "", "size": "96x72", "encoding": "mono8", "frames": "7",
        "refused_settings": "", "compressed_failures": "2",
        "calibration": "the simulated rig's true intrinsics", "last_camera_error": ""}
    assert (bursts.name, bursts.hardware_id, bursts.level, bursts.message) == (
        "driver: bursts", "sim", DiagnosticStatus.OK, "ok")
    values = _values(bursts)
    assert list(values) == ["bursts_ok", "bursts_failed", "last_error", "last_burst_ms",
                            "burst_ms_median", "burst_ms_max", "last_publish_ms",
                            "publish_ms_median", "publish_ms_max", "timing_window",
                            "rate_requested", "rate_achieved"]
    assert (values["bursts_ok"], values["bursts_failed"], values["timing_window"]) == (
        "1", "0", "1")
    assert (values["last_publish_ms"], values["publish_ms_median"],
            values["publish_ms_max"]) == ("1.25", "1.25", "1.25")
    assert (values["rate_requested"], values["rate_achieved"]) == ("0", "")


def test_a_lost_board_is_an_error_and_a_waited_one_a_warning(core):
    core.board.lost("cable pulled")
    board, _, _ = driver_statuses("driver", core, 0)
    assert board.level == DiagnosticStatus.ERROR
    assert board.message.startswith("disconnected: cable pulled; next attempt in ")
    assert _values(board)["disconnects"] == "1"
    core.board.state = BoardState.WAITING
    board, _, _ = driver_statuses("driver", core, 0)
    assert board.level == DiagnosticStatus.WARN and board.message.startswith("waiting: ")


def test_a_burst_failed_at_the_camera_warns_on_both(core, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("sensor on fire")

    monkeypatch.setattr(core.renderer.rig, "render", broken)
    reason = core.capture(PLAN, with_dark=False).reason
    _, camera, bursts = driver_statuses("driver", core, 0)
    assert camera.level == DiagnosticStatus.WARN
    assert camera.message == f"last burst failed at the camera: {reason}"
    assert bursts.level == DiagnosticStatus.WARN
    assert bursts.message == f"last burst failed: {reason}"
    assert _values(bursts)["bursts_failed"] == "1"


def test_continuous_capture_behind_its_rate_warns(core):
    core.capture_rate.set_rate(10.0, time.monotonic() - 6.0)
    core.capture_rate.captured(time.monotonic() - 1.0)
    _, _, bursts = driver_statuses("driver", core, 0)
    assert bursts.level == DiagnosticStatus.WARN
    assert bursts.message == (
        "continuous capture delivers 0.2 bursts/s of the 10 asked for: a burst takes longer "
        "than 1/rate (see burst_ms_median and publish_ms_median); lower rate")
    assert (_values(bursts)["rate_requested"], _values(bursts)["rate_achieved"]) == (
        "10", "0.20")
