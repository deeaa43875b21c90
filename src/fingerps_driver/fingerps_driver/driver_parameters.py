"""The driver's parameters: one table of names, defaults, descriptors and checks, declared in
one call, and read back into the settings of the board, the camera and the burst.

Every check refuses a bad value with a reason (``fingerps_ros.parameters``), at start and
when it is set at run time. Checks and defaults that depend on another parameter
(``led_order`` on ``led_count``) read it through ``Values`` when they run; that parameter
is declared before them and read-only.
"""

from __future__ import annotations

import array
from collections.abc import Callable
from typing import Any

import numpy as np

from fingerps_calib.intrinsics.camera_info_url import DEFAULT_CAMERA_INFO_URL
from fingerps_driver.board.backoff import Backoff
from fingerps_driver.board.board_connection import BoardSettings
from fingerps_driver.board.board_protocol import MAX_TRIGGER_US
from fingerps_driver.cameras.camera_setup import CameraBackend, CameraSettings, SimSettings
from fingerps_driver.capture.burst_plan import (
    MAX_EXPOSURE_S,
    MIN_EXPOSURE_S,
    BurstPlan,
    check_exposures,
    check_led_order,
    check_levels,
    make_plan,
)
from fingerps_driver.simulation import Reflectance, RigConfig, Scene
from fingerps_driver.simulation.rig_config import MAX_PITCH_DEG, MAX_ROLL_DEG, MAX_YAW_DEG
from fingerps_ros.parameter_table import ParameterRow, one_of

Values = Callable[[str], Any]
"""The node's current value of a parameter, by name."""

_BOARD = BoardSettings()
_CAMERA = CameraSettings()
# The table's defaults are these settings' defaults (each written once, in its dataclass).

FINGER_POSE = ("sim.finger_identity", "sim.finger_roll_deg", "sim.finger_yaw_deg",
               "sim.finger_pitch_deg", "sim.finger_shift_mm")
"""The parameters whose change rebuilds the simulated finger."""


def _sphere_center_problem(value: list[float]) -> str | None:
    if len(value) != 3 or not all(np.isfinite(value)):
        return "must be three finite numbers [x, y, z] in metres"
    if value[2] <= 0.02:
        return "z must be more than 0.02 m in front of the camera"
    return None


def _finger_shift_problem(value: list[float]) -> str | None:
    if len(value) != 2 or not all(np.isfinite(value)) or max(abs(v) for v in value) > 5.0:
        return ("must be two finite numbers [dx, dy] in mm (the apex's shift in the image "
                "plane), each within +-5")
    return None


def _finger_angle(name: str, description: str, limit: float, beyond: str = "") -> ParameterRow:
    """A rotation of the simulated finger, degrees, 0 by default and within +-``limit``."""
    reason = f"must be within +-{limit:g} degrees{beyond}"
    return ParameterRow(name, 0.0, description, min_value=-limit, max_value=limit,
                        check=lambda v: None if abs(v) <= limit else reason)


def _numbers(value: object) -> list[float] | None:
    """A dynamically typed per-LED array as floats (None when not set); see _numbers_problem."""
    return None if value is None else [float(v) for v in value]  # type: ignore[attr-defined]


def _numbers_problem(value: object) -> str | None:
    """Why a dynamically typed array parameter is not a list of numbers, or None."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple, array.array)) or any(
            isinstance(v, (bool, str, bytes)) for v in value):
        return "must be a list of numbers, one per LED, or empty"
    return None


def _per_led(name: str, description: str,
             check: Callable[[list[float] | None, int], str | None],
             led_count: Callable[[], int]) -> ParameterRow:
    """A per-LED array: [] by default, dynamically typed, its numbers checked by ``check``.

    Not statically typed: a statically typed parameter with no value makes rclpy's
    get_parameters service answer nothing at all, so `ros2 param dump` printed {} (and
    rclpy types [] as bytes).
    """
    return ParameterRow(name, [], description, dynamic_typing=True,
                        check=lambda v: _numbers_problem(v) or check(_numbers(v), led_count()))


def driver_parameters(value: Values) -> tuple[ParameterRow, ...]:
    """The driver's parameters in declaration order; ``value`` reads one already declared."""
    def led_count() -> int:
        return int(value("led_count"))

    return (
        # the board
        ParameterRow(
            "port", _BOARD.port,
            "Serial device of the LED board (e.g. /dev/ttyACM0, or the emulator's --link), "
            "or 'sim' for the built-in board emulator on a pseudo-terminal", read_only=True),
        ParameterRow(
            "baudrate", _BOARD.baudrate, "Serial baud rate", min_value=1200, max_value=4_000_000,
            integer=True, read_only=True),
        ParameterRow(
            "board_timeout", _BOARD.timeout_s, "Seconds one attempt waits for the board's reply",
            min_value=0.005, max_value=2.0, read_only=True),
        ParameterRow(
            "board_retries", _BOARD.retries,
            "Resends of a command after a lost, late or corrupted reply", min_value=0,
            max_value=10, integer=True, read_only=True),
        ParameterRow(
            "wait_for_port", _BOARD.wait_for_port,
            "If the board is missing at start, wait and retry (with back-off) instead of "
            "exiting with code 2", read_only=True),
        ParameterRow(
            "reconnect_initial_s", _BOARD.backoff.initial_s,
            "First delay before reopening a lost board, seconds; doubled per failed attempt",
            min_value=0.01, max_value=60.0, read_only=True),
        ParameterRow(
            "reconnect_max_s", _BOARD.backoff.max_s,
            "Longest delay between attempts to reopen a lost board, seconds",
            check=lambda v: None if v >= value("reconnect_initial_s")
            else "must be >= reconnect_initial_s",
            min_value=0.01, max_value=600.0, read_only=True),
        ParameterRow(
            "led_count", _BOARD.led_count, "Number of LEDs on the board", min_value=3, max_value=16,
            integer=True, read_only=True),
        ParameterRow(
            "trigger_delay_us", _BOARD.trigger_delay_us,
            "Camera trigger: microseconds from the LEDs' switch to the trigger pulse (the "
            "board's TRIG command; the AVR firmware rounds up to 16 us)",
            min_value=0, max_value=MAX_TRIGGER_US, integer=True, read_only=True),
        ParameterRow(
            "trigger_width_us", _BOARD.trigger_width_us,
            "Camera trigger: pulse width in microseconds after every LED switch; 0 = no "
            "trigger (a board without one is then fine). Set at connect and reconnect",
            min_value=0, max_value=MAX_TRIGGER_US, integer=True, read_only=True),
        ParameterRow(
            "led_order", lambda: list(range(led_count())),
            "LEDs captured in a burst, in capture order (0-based, each at most once; "
            "default all in index order). Bursts are published sorted by LED index",
            check=lambda v: check_led_order(list(v), led_count())),
        # exposure and levels
        ParameterRow(
            "exposure_time", 0.01, "Exposure time per frame, seconds",
            min_value=MIN_EXPOSURE_S, max_value=MAX_EXPOSURE_S),
        _per_led(
            "exposure_times",
            "Exposure time of each LED, seconds, indexed by LED (one per LED); "
            "empty: exposure_time for all", check_exposures, led_count),
        ParameterRow(
            "led_level", 1.0, "Relative LED drive level, 0..1", min_value=0.0,
            max_value=1.0),
        _per_led(
            "led_levels",
            "Relative drive level 0..1 of each LED, indexed by LED (one per LED); "
            "empty: led_level for all", check_levels, led_count),
        # capture modes
        ParameterRow(
            "rate", 0.0, "Continuous capture rate in bursts per second; 0 = only on request",
            min_value=0.0, max_value=30.0),
        ParameterRow(
            "with_dark_frame", False,
            "Add an all-LEDs-off frame to continuous bursts (ambient subtraction)"),
        # the camera
        ParameterRow(
            "camera", _CAMERA.backend.value,
            "Camera backend: 'sim' (the simulated rig), 'v4l2' (a real camera through "
            "OpenCV/V4L2) or 'folder' (replay of a DiLiGenT-layout image folder)",
            check=one_of(*(c.value for c in CameraBackend)), read_only=True),
        ParameterRow(
            "camera_device", _CAMERA.device,
            "v4l2: device path (e.g. /dev/video0 or /dev/v4l/by-id/...) or index",
            read_only=True),
        ParameterRow(
            "camera_folder", _CAMERA.folder,
            "folder: the folder holding filenames.txt; the i-th listed image is LED i's",
            read_only=True),
        ParameterRow(
            "camera_width", _CAMERA.width,
            "Image width to ask for (v4l2), to expect (folder) or to render (sim); 0 = the "
            "camera's", check=lambda v: None if v >= 0 else "must be >= 0 (0 = default)",
            min_value=0, max_value=16384, integer=True, read_only=True),
        ParameterRow(
            "camera_height", _CAMERA.height, "Image height, as camera_width",
            check=lambda v: None if v >= 0 else "must be >= 0 (0 = default)",
            min_value=0, max_value=16384, integer=True, read_only=True),
        ParameterRow(
            "camera_pixel_format", _CAMERA.pixel_format,
            "mono8 or mono16; empty = the camera's (v4l2: mono8, folder: the images' bit "
            "depth, sim: sim.bit_depth)", check=one_of("", "mono8", "mono16"),
            read_only=True),
        ParameterRow(
            "camera_fourcc", _CAMERA.fourcc,
            "v4l2: pixel format to ask for (GREY, YUYV, MJPG, 'Y16 '...); empty = mono8: "
            "the camera's default, mono16: 'Y16 '",
            check=lambda v: None if len(v) in (0, 4) and v.isascii()
            else "must be four ASCII characters (e.g. GREY, YUYV, MJPG) or empty",
            read_only=True),
        ParameterRow(
            "camera_fps", _CAMERA.fps, "v4l2: frame rate to ask for; 0 = the camera's",
            min_value=0.0, max_value=1000.0, read_only=True),
        ParameterRow(
            "camera_gain", _CAMERA.gain,
            "v4l2: gain in the device's units; negative = leave it as it is",
            min_value=-1.0, max_value=1e6, read_only=True),
        ParameterRow(
            "camera_discard_frames", _CAMERA.discard_frames,
            "v4l2: frames dropped after each LED switch before the one kept (a free-running "
            "camera's frame in progress mixes two lights)", min_value=0, max_value=10,
            integer=True, read_only=True),
        ParameterRow(
            "camera_info_url", _CAMERA.camera_info_url,
            "Where the camera's calibration is loaded from and set_camera_info stores it "
            "(camera_info_manager's rules): file:///path.yaml, package://pkg/path.yaml, "
            "${NAME} and ${ROS_HOME} substituted; empty = "
            f"{DEFAULT_CAMERA_INFO_URL}. Missing: the sim rig's true intrinsics, or none "
            "(K = 0) for the other cameras", read_only=True),
        ParameterRow(
            "camera_info_file", _CAMERA.camera_info_file,
            "Older form of camera_info_url: a camera_info YAML path, which must exist and "
            "fit the camera (else exit 2); empty = use camera_info_url", read_only=True),
        ParameterRow(
            "frame_id", "fingerps_camera_optical_frame",
            "TF frame of the camera's optical frame (REP-103)", read_only=True),
        ParameterRow(
            "camera_name", _CAMERA.camera_name,
            "Camera name: ${NAME} of camera_info_url, written into the calibration file "
            "(letters, digits, _)", read_only=True),
        # the simulated rig
        ParameterRow(
            "sim.scene", _CAMERA.sim.scene.value,
            "What the simulated camera sees: finger, sphere, white_target or empty",
            check=one_of(*(s.value for s in Scene))),
        ParameterRow(
            "sim.reflectance", _CAMERA.sim.reflectance.value,
            "Reflectance the simulated rig renders the finger with: hk or lambert",
            check=one_of(*(r.value for r in Reflectance)), read_only=True),
        ParameterRow(
            "sim.bit_depth", _CAMERA.sim.bit_depth, "Simulated sensor bit depth: 8 or 12",
            check=lambda v: None if v in (8, 12) else "must be 8 or 12",
            min_value=8, max_value=12, integer=True, read_only=True),
        ParameterRow(
            "sim.seed", _CAMERA.sim.seed, "Seed of the simulated sensor noise", min_value=0,
            integer=True, read_only=True),
        ParameterRow(
            "sim.sphere_center", list(_CAMERA.sim.sphere_center_optical_m),
            "Where the simulated calibration sphere is, [x, y, z] metres in the optical "
            "frame; move it between calibrate_lights calls (add_placement) to estimate the "
            "LED positions", check=_sphere_center_problem),
        ParameterRow(
            "sim.finger_motion_px", list(_CAMERA.sim.motion_px),
            "Simulated finger motion during a burst, [du, dv] pixels: frame i of n LEDs is "
            "shifted by i/n of it, the repeated first LED (repeat_first_led) by all of it",
            check=lambda v: None if len(v) == 2 and all(np.isfinite(v))
            and max(abs(x) for x in v) <= 100 else
            "must be two finite numbers [du, dv] in pixels, each within +-100"),
        ParameterRow(
            "sim.finger_motion_bursts", _CAMERA.sim.motion_bursts,
            "Bursts the finger moves in once sim.finger_motion_px is set (counted from "
            "then); 0 = every burst", min_value=0, max_value=1_000_000, integer=True),
        ParameterRow(
            "sim.finger_identity", -1,
            "The simulated finger's fingerprint: -1 the analytic spiral, n >= 0 the synthetic "
            "fingerprint of identity n (SFinGe-style, ~1 s to generate); changing it or the "
            "pose rebuilds the finger (a few seconds) before the next burst",
            check=lambda v: None if -1 <= v <= 2**31 - 1 else
            "must be -1 (the analytic spiral) or a fingerprint identity 0..2^31-1",
            min_value=-1, max_value=2**31 - 1, integer=True),
        _finger_angle(
            "sim.finger_roll_deg",
            "Rotation of the simulated finger about its own axis, degrees (+ brings the skin "
            "at the apex towards +x)", MAX_ROLL_DEG,
            " (beyond, the skin seen leaves the rolled print)"),
        _finger_angle(
            "sim.finger_yaw_deg",
            "Rotation of the simulated finger about the optical axis through its apex, "
            "degrees, from +x towards +y (clockwise as displayed)", MAX_YAW_DEG),
        _finger_angle(
            "sim.finger_pitch_deg",
            "Then its rotation about the optical x axis through its apex, degrees, from +y "
            "towards +z (+ brings the tip towards the camera)", MAX_PITCH_DEG,
            " (beyond, a margin comes near grazing)"),
        ParameterRow(
            "sim.finger_shift_mm", [0.0, 0.0],
            "Shift [dx, dy] of the simulated finger's apex in the image plane, mm (optical "
            "x right, y down), each within +-5", check=_finger_shift_problem),
        ParameterRow(
            "sim.board_control", _BOARD.control,
            "Control socket of a board_emulator process (its --control): with a port other "
            "than 'sim', the sim and folder cameras see the LEDs that emulator has lit",
            read_only=True),
    )


def board_settings(value: Values) -> BoardSettings:
    """The board's settings from the parameters."""
    initial_s = float(value("reconnect_initial_s"))
    return BoardSettings(
        port=str(value("port")), led_count=int(value("led_count")),
        baudrate=int(value("baudrate")), timeout_s=float(value("board_timeout")),
        retries=int(value("board_retries")), wait_for_port=bool(value("wait_for_port")),
        backoff=Backoff(initial_s, max(float(value("reconnect_max_s")), initial_s)),
        control=str(value("sim.board_control")),
        trigger_delay_us=int(value("trigger_delay_us")),
        trigger_width_us=int(value("trigger_width_us")))


def burst_plan(value: Values) -> BurstPlan:
    """The plan of the next burst from the parameters in force."""
    return make_plan(
        led_count=int(value("led_count")),
        led_order=list(value("led_order")),
        exposure_time=float(value("exposure_time")),
        exposure_times=_numbers(value("exposure_times")) or [],
        led_level=float(value("led_level")),
        led_levels=_numbers(value("led_levels")) or [])


def finger_config(value: Values) -> dict[str, Any]:
    """``FingertipShape`` fields of the simulated finger's identity and pose from
    sim.finger_*."""
    identity = int(value("sim.finger_identity"))
    shift = [1e-3 * float(v) for v in value("sim.finger_shift_mm")]
    x, y, z = RigConfig().finger.apex_optical_m
    return {
        "identity": None if identity < 0 else identity,
        "roll_deg": float(value("sim.finger_roll_deg")),
        "yaw_deg": float(value("sim.finger_yaw_deg")),
        "pitch_deg": float(value("sim.finger_pitch_deg")),
        "apex_optical_m": (x + shift[0], y + shift[1], z),
    }


def camera_settings(value: Values) -> CameraSettings:
    """The camera's settings (with the simulated rig's) from the parameters."""
    sim = SimSettings(
        scene=Scene(value("sim.scene")), reflectance=Reflectance(value("sim.reflectance")),
        bit_depth=int(value("sim.bit_depth")), seed=int(value("sim.seed")),
        sphere_center_optical_m=tuple(value("sim.sphere_center")),
        finger=finger_config(value),
        motion_px=tuple(float(v) for v in value("sim.finger_motion_px")),
        motion_bursts=int(value("sim.finger_motion_bursts")))
    return CameraSettings(
        backend=CameraBackend(value("camera")), device=str(value("camera_device")),
        folder=str(value("camera_folder")), width=int(value("camera_width")),
        height=int(value("camera_height")), pixel_format=str(value("camera_pixel_format")),
        fourcc=str(value("camera_fourcc")), fps=float(value("camera_fps")),
        gain=float(value("camera_gain")),
        discard_frames=int(value("camera_discard_frames")),
        exposure_s=burst_plan(value).exposures_s[0], led_count=int(value("led_count")),
        camera_name=str(value("camera_name")), camera_info_url=str(value("camera_info_url")),
        camera_info_file=str(value("camera_info_file")), sim=sim)
