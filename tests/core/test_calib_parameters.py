"""Tests of fingerps_calib.calib_parameters: the checks of calib_node's parameters and the
default calibration directory (the declarations are checked by the graph tests)."""

from __future__ import annotations

import array
import math

import pytest

from fingerps_calib.calib_parameters import (
    CALIB_PARAMETERS,
    CHECKED_AT_START,
    check_camera_name,
    check_reference_point,
    check_sphere_radius,
    default_calibration_dir,
)
from fingerps_calib.calibration_keeper import CalibrationSettings
from fingerps_ros.parameter_table import check_finite


def test_reference_point():
    assert check_reference_point(array.array("d", [0.0, 0.0025, 0.09])) is None
    for bad in ([0.0, 0.0, math.inf], [math.nan, 0.0, 0.09], [0.0, 0.0, -0.09], [0.0, 0.09],
                "abc", None):
        assert "three finite numbers (x, y, z) in metres with z > 0" in \
            check_reference_point(bad)


def test_camera_name_radius_and_finite_numbers():
    assert check_camera_name("rig_2") is None
    assert check_camera_name("  ").startswith("must not be empty")
    assert check_sphere_radius(0.004) is None
    for bad in (math.inf, math.nan, 1e-300, 1.0):
        assert check_sphere_radius(bad) == (
            "must be a finite radius in metres between 0.0005 and 0.05 (0.5-50 mm), e.g. "
            "0.004 for a ball of 8 mm")
    assert check_finite(5.0) is None
    assert check_finite(math.nan) == check_finite("x") == "must be a finite number"


def test_default_calibration_dir(monkeypatch: pytest.MonkeyPatch, tmp_path):
    monkeypatch.setenv("ROS_HOME", str(tmp_path))
    assert default_calibration_dir() == str(tmp_path / "fingerps" / "calibration")
    monkeypatch.delenv("ROS_HOME")
    assert default_calibration_dir().endswith("/.ros/fingerps/calibration")


def test_the_settings_defaults_are_the_parameters_defaults():
    assert CalibrationSettings() == CalibrationSettings(
        camera_name="fingerps_sim", sphere_radius_m=0.004,
        reference_point_optical_m=(0.0, 0.0025, 0.09), sphere_distance_tolerance=0.3,
        flat_field_degree=4, mono16_full_scale=4095.0)


def test_every_parameter_with_a_check_is_checked_at_start():
    # CHECKED_AT_START orders the start-up message by hand; it must name exactly the rows
    # that have a check, so that a new check is not left out of the start
    with_check = {row.name for row in CALIB_PARAMETERS if row.check is not None}
    assert sorted(CHECKED_AT_START) == sorted(with_check)
    assert len(set(CHECKED_AT_START)) == len(CHECKED_AT_START)
