"""The driver's parameter table without a node: names in order, defaults, descriptors, the
checks' reasons, and the settings read back from the values."""

from __future__ import annotations

from typing import Any

import pytest
from rcl_interfaces.msg import ParameterDescriptor

from fingerps_driver import driver_parameters as table
from fingerps_driver.board.backoff import Backoff
from fingerps_driver.board.board_connection import BoardSettings
from fingerps_driver.cameras.camera_setup import CameraBackend, CameraSettings, SimSettings
from fingerps_driver.simulation import RigConfig
from fingerps_ros.parameters import row_descriptor


def _declared(**overrides: Any) -> dict[str, Any]:
    """The values the node declares, in order (a callable default sees the ones before)."""
    values: dict[str, Any] = {}
    for row in table.driver_parameters(values.__getitem__):
        values[row.name] = overrides.get(row.name, row.default_value())
    return values


def _rows(values: dict[str, Any] | None = None) -> dict[str, Any]:
    values = _declared() if values is None else values
    return {row.name: row for row in table.driver_parameters(values.__getitem__)}


def _descriptor(name: str) -> ParameterDescriptor:
    return row_descriptor(_rows()[name])


def test_every_parameter_once_in_declaration_order():
    names = [row.name for row in table.driver_parameters(_declared().__getitem__)]
    assert len(names) == len(set(names)) == 44
    assert names[:10] == ["port", "baudrate", "board_timeout", "board_retries", "wait_for_port",
                          "reconnect_initial_s", "reconnect_max_s", "led_count",
                          "trigger_delay_us", "trigger_width_us"]
    assert names[-1] == "sim.board_control" and set(table.FINGER_POSE) <= set(names)


def test_defaults_follow_the_parameters_declared_before():
    assert _declared()["led_order"] == list(range(7))
    assert _declared(led_count=4)["led_order"] == [0, 1, 2, 3]
    assert _declared()["sim.sphere_center"] == list(RigConfig().sphere.center_optical_m)


def test_descriptors_carry_ranges_and_flags():
    led_count = _descriptor("led_count")
    assert led_count.read_only and led_count.description == "Number of LEDs on the board"
    assert [(r.from_value, r.to_value) for r in led_count.integer_range] == [(3, 16)]
    rate = _descriptor("rate")
    assert not rate.read_only
    assert [(r.from_value, r.to_value) for r in rate.floating_point_range] == [(0.0, 30.0)]
    for name in ("trigger_delay_us", "trigger_width_us"):
        trigger = _descriptor(name)
        assert trigger.read_only and "trigger" in trigger.description
        assert [(r.from_value, r.to_value) for r in trigger.integer_range] == [(0, 65535)]
    assert _descriptor("exposure_times").dynamic_typing
    assert _descriptor("led_levels").dynamic_typing
    assert not _descriptor("led_order").dynamic_typing
    assert "file://${ROS_HOME}/camera_info/${NAME}.yaml" in \
        _descriptor("camera_info_url").description


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("led_order", [0, 0, 1], "names LED(s) [0] more than once"),
    ("led_order", [5], "names LED(s) [5] beyond the board's 0..4"),
    ("exposure_times", [0.1], "has 1 entries for 5 LEDs; give one per LED, or none"),
    ("exposure_times", ["a"], "must be a list of numbers, one per LED, or empty"),
    ("led_levels", [True] * 5, "must be a list of numbers, one per LED, or empty"),
    ("led_levels", [2.0] * 5, "holds [2.0, 2.0, 2.0, 2.0, 2.0]: levels are in 0..1"),
    ("reconnect_max_s", 0.5, "must be >= reconnect_initial_s"),
    ("camera", "usb", "must be one of sim, v4l2, folder"),
    ("camera_fourcc", "YU", "must be four ASCII characters (e.g. GREY, YUYV, MJPG) or empty"),
    ("sim.bit_depth", 10, "must be 8 or 12"),
    ("sim.sphere_center", [0.0, 0.0, 0.01], "z must be more than 0.02 m in front of the camera"),
    ("sim.finger_shift_mm", [0.0, 6.0],
     "must be two finite numbers [dx, dy] in mm (the apex's shift in the image plane), "
     "each within +-5"),
    ("sim.finger_motion_px", [1.0],
     "must be two finite numbers [du, dv] in pixels, each within +-100"),
    ("sim.finger_roll_deg", 50.0,
     "must be within +-45 degrees (beyond, the skin seen leaves the rolled print)"),
])
def test_checks_refuse_with_a_reason(name, value, reason):
    rows = _rows(_declared(led_count=5, reconnect_initial_s=1.0))
    assert rows[name].check(value) == reason


@pytest.mark.parametrize(("name", "value"), [
    ("exposure_times", None), ("exposure_times", []), ("led_levels", [0.5] * 7),
    ("reconnect_max_s", 0.5), ("camera_fourcc", "Y16 "), ("sim.finger_identity", -1),
])
def test_checks_take_good_values(name, value):
    assert _rows()[name].check(value) is None


def test_the_defaults_read_back_as_the_settings_defaults():
    values = _declared()
    assert table.board_settings(values.__getitem__) == BoardSettings(backoff=Backoff(0.5, 5.0))
    settings = table.camera_settings(values.__getitem__)
    assert settings == CameraSettings(sim=SimSettings(finger=settings.sim.finger))
    assert settings.sim.finger == table.finger_config(values.__getitem__)
    plan = table.burst_plan(values.__getitem__)
    assert plan.led_order == tuple(range(7)) and plan.exposures_s == (0.01,) * 7


def test_settings_read_what_is_set():
    values = _declared(port="/dev/ttyACM0", reconnect_initial_s=2.0, reconnect_max_s=1.0,
                       camera="v4l2", camera_device="2", led_order=[3, 1],
                       trigger_delay_us=100, trigger_width_us=50,
                       exposure_times=[0.001 * (i + 1) for i in range(7)],
                       **{"sim.board_control": "/tmp/ctl", "sim.finger_identity": 4,
                          "sim.finger_shift_mm": [1.0, -2.0]})
    board = table.board_settings(values.__getitem__)
    assert (board.port, board.control, board.backoff) == ("/dev/ttyACM0", "/tmp/ctl",
                                                          Backoff(2.0, 2.0))
    assert (board.trigger_delay_us, board.trigger_width_us) == (100, 50)
    camera = table.camera_settings(values.__getitem__)
    assert (camera.backend, camera.device, camera.exposure_s) == (CameraBackend.V4L2, "2",
                                                                  0.004)
    finger = camera.sim.finger
    x, y, z = RigConfig().finger.apex_optical_m
    assert finger["identity"] == 4
    assert finger["apex_optical_m"] == pytest.approx((x + 0.001, y - 0.002, z))
    plan = table.burst_plan(values.__getitem__)
    assert plan.led_order == (3, 1) and plan.exposures_s == (0.004, 0.002)
