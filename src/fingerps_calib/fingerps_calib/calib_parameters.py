"""calib_node's parameters: their table, their checks, and the settings they make.

Each parameter is declared (`CALIB_PARAMETERS`) with its description and range (``ros2
param describe``); the checks refuse a bad value set at run time with a reason, and a bad
value at start stops the node with one line. `calibration_settings` reads the values a
calibration uses now.
"""

from __future__ import annotations

import math
import os

from rclpy.node import Node

from fingerps_calib.calibration_keeper import CalibrationSettings
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.sphere_silhouette import RADIUS_RANGE_M, check_radius
from fingerps_recon.photometric.full_scale import MONO16_FULL_SCALE
from fingerps_ros.node_runner import StartupError
from fingerps_ros.parameter_table import ParameterRow, check_finite
from fingerps_ros.parameters import ParameterChecks, declare_parameters

_DEFAULTS = CalibrationSettings()


def default_calibration_dir() -> str:
    """``$ROS_HOME/fingerps/calibration`` (ROS_HOME defaults to ~/.ros)."""
    ros_home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    return os.path.join(ros_home, "fingerps", "calibration")


def check_reference_point(value: object) -> str | None:
    """Three finite numbers with z > 0, or the reason not."""
    try:
        point = [float(x) for x in value]  # a ROS double array is an array.array
    except (TypeError, ValueError):
        point = []
    if len(point) != 3 or not all(math.isfinite(x) for x in point) or not point[2] > 0:
        return ("must be three finite numbers (x, y, z) in metres with z > 0 (in front of "
                "the camera), e.g. [0.0, 0.0025, 0.09]")
    return None


def check_camera_name(value: object) -> str | None:
    """A name that is not blank, or the reason not."""
    if not isinstance(value, str) or not value.strip():
        return ("must not be empty: it names the camera in every calibration (and a saved "
                "calibration is loaded only for the same name), e.g. fingerps_sim")
    return None


def check_sphere_radius(value: object) -> str | None:
    """A radius within `RADIUS_RANGE_M`, or the reason not."""
    try:
        check_radius(value)
    except FingerpsCalibError:
        lo, hi = RADIUS_RANGE_M
        return (f"must be a finite radius in metres between {lo:g} and {hi:g} "
                f"({1e3 * lo:g}-{1e3 * hi:g} mm), e.g. 0.004 for a ball of 8 mm")
    return None


CALIB_PARAMETERS = (
    ParameterRow(
        "sphere_radius", _DEFAULTS.sphere_radius_m,
        "Radius of the calibration sphere, metres (used when a request gives 0); "
        "0.0005-0.05 (a sphere seen whole by the camera, its silhouette wide enough to fit)",
        min_value=RADIUS_RANGE_M[0], max_value=RADIUS_RANGE_M[1],
        check=check_sphere_radius),
    ParameterRow(
        "capture_timeout", 5.0,
        "Seconds to wait for the driver's burst when a request carries no images",
        min_value=0.1, max_value=60.0, check=check_finite),
    ParameterRow(
        "flat_field_degree", _DEFAULTS.flat_field_degree,
        "Degree of the smooth 2D polynomial fitted to each white-target image (so paper "
        "texture and noise do not enter the flat-field maps)", min_value=1, max_value=10,
        integer=True),
    ParameterRow(
        "camera_name", _DEFAULTS.camera_name,
        "Camera name written into calibrations; a saved calibration of another camera "
        "is not loaded", constraints="not empty", check=check_camera_name),
    ParameterRow(
        "calibration_dir", default_calibration_dir,
        "Directory where the calibration in force is saved (lights.yaml, "
        "flat_field.yaml + .npz, pictures) and loaded from at start; empty: neither",
        read_only=True),
    ParameterRow(
        "camera_info_file", "",
        "camera_info YAML (camera_calibration format) with the intrinsics; empty: use the "
        "driver's camera_info", read_only=True),
    ParameterRow(
        "reference_point", list(_DEFAULTS.reference_point_optical_m),
        "Point (x, y, z) in metres, optical frame, where the finger rests (the default: "
        "the simulated rig's fingertip apex); the directions of a calibration from two "
        "or more sphere placements start there, and its distance is the expected "
        "distance of the sphere", constraints="three finite numbers, z > 0",
        check=check_reference_point),
    ParameterRow(
        "sphere_distance_tolerance", _DEFAULTS.sphere_distance_tolerance,
        "The sphere centre must lie within this fraction of the reference point's "
        "distance from the camera (a wrong sphere radius shows as a wrong distance)",
        min_value=0.05, max_value=0.9, check=check_finite),
    MONO16_FULL_SCALE,
)
"""calib_node's parameter table, in the order they are declared."""

CHECKED_AT_START = ("reference_point", "camera_name", "sphere_radius", "capture_timeout",
                    "sphere_distance_tolerance", "mono16_full_scale")
"""The parameters with a check, in the order a start-up error names their bad values."""


def declare_calib_parameters(node: Node) -> ParameterChecks:
    """Declare `CALIB_PARAMETERS` on ``node``; returns the checks.

    The checks come into force after the last declaration, so that a start with bad
    values names every one of them at once.

    Raises
    ------
    StartupError
        A value given at start fails its check (the message names each).
    UnknownParameterError
        A parameter given at start that calib_node does not have.
    """
    checks = declare_parameters(node, CALIB_PARAMETERS, check_while_declaring=False)
    checks.refuse_unknown_overrides(node)
    problems = checks.problems([node.get_parameter(name) for name in CHECKED_AT_START])
    if problems:
        raise StartupError("; ".join(problems))
    return checks


def calibration_settings(node: Node) -> CalibrationSettings:
    """The settings of a calibration made now, from ``node``'s parameters."""
    def value(name: str) -> object:
        return node.get_parameter(name).value

    reference = [float(x) for x in value("reference_point")]
    return CalibrationSettings(
        camera_name=str(value("camera_name")),
        sphere_radius_m=float(value("sphere_radius")),
        reference_point_optical_m=(reference[0], reference[1], reference[2]),
        sphere_distance_tolerance=float(value("sphere_distance_tolerance")),
        flat_field_degree=int(value("flat_field_degree")),
        mono16_full_scale=float(value("mono16_full_scale")))
