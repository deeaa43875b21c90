"""driver_node: switches the LEDs over serial, captures and tags bursts, publishes them.

Thin ROS adapter: parameters, QoS, message conversion, the board's connection state; the
sequencing is ``fingerps_driver.capture.burst.capture_burst``, the board protocol
``fingerps_driver.board.led_board``, the cameras ``camera``, ``camera_opencv`` and
``camera_folder``.

With ``port`` = ``sim`` (the default) the node starts the board emulator on a real
pseudo-terminal in this process and drives it through pyserial exactly as it would drive the
real board; the simulated camera renders whatever LEDs the emulator has actually lit. With
another port and ``camera`` = ``sim`` (or ``folder``), ``sim.board_control`` names the
control socket of a ``board_emulator`` process, through which the camera sees what that
emulator has lit (the serial port stays the only way LEDs are switched).

The board: a disconnect (a burst fails with ``BoardDisconnectedError``, or the port vanishes)
closes the port, reports it (log and diagnostics ERROR) and retries opening it from a timer
with exponential back-off (``reconnect_initial_s`` .. ``reconnect_max_s``); captures asked
for meanwhile fail at once with a message saying so. ``wait_for_port`` makes a board missing
at start the same wait instead of exit code 2.
"""

from __future__ import annotations

import array
import collections
import os
import statistics
import threading
import time
from dataclasses import dataclass, replace
from enum import Enum

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from sensor_msgs.srv import SetCameraInfo
from std_msgs.msg import Header

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_conversion import (
    camera_info_to_intrinsics,
    intrinsics_to_camera_info,
)
from fingerps_calib.intrinsics.camera_info_url import DEFAULT_CAMERA_INFO_URL
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics
from fingerps_driver.board.backoff import Backoff
from fingerps_driver.board.board_emulator import BoardEmulator, BoardEmulatorControl
from fingerps_driver.board.board_protocol import mask_to_indices
from fingerps_driver.board.led_board import BoardError, BoardRejectedError, LedBoard
from fingerps_driver.cameras.camera import Camera, CameraError, SimulatedCamera
from fingerps_driver.cameras.camera_folder import FolderCamera
from fingerps_driver.cameras.camera_info_manager import CameraInfoManager
from fingerps_driver.cameras.camera_opencv import OpenCvCamera, parse_device
from fingerps_driver.capture.burst import BurstResult, CapturedFrame, capture_burst
from fingerps_driver.capture.burst_plan import (
    MAX_EXPOSURE_S,
    MIN_EXPOSURE_S,
    BurstPlan,
    check_exposures,
    check_led_order,
    check_levels,
    make_plan,
)
from fingerps_driver.capture.capture_rate import CaptureRate
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import Reflectance, RigConfig, Scene, SimulatedRig
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import qos, topics
from fingerps_ros.compressed_topics import CompressedTopics
from fingerps_ros.image_conversion import array_to_image
from fingerps_ros.node_runner import StartupError, run_node
from fingerps_ros.parameters import ParameterChecks, descriptor, one_of

SIM_PORT = "sim"
DARK_LED = TaggedFrame.LED_DARK
TIMING_WINDOW = 200
"""Bursts over which the diagnostics' burst and publish time medians/maxima are taken."""


class CameraBackend(Enum):
    """The ``camera`` parameter."""

    SIM = "sim"
    V4L2 = "v4l2"
    FOLDER = "folder"


class BoardState(Enum):
    """Connection state of the LED board."""

    CONNECTED = "connected"
    DISCONNECTED = "disconnected"  # lost while running; reconnecting
    WAITING = "waiting"  # not there at start (wait_for_port); retrying


@dataclass
class _Counters:
    ok: int = 0
    failed: int = 0
    last_error: str = ""
    last_burst_failed: bool = False
    last_burst_ms: float = 0.0
    last_publish_ms: float = 0.0
    camera_error: str = ""
    board_error: str = ""
    disconnects: int = 0
    reconnects: int = 0
    reconnect_attempts: int = 0


def _stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _sphere_center_problem(value: list[float]) -> str | None:
    if len(value) != 3 or not all(np.isfinite(value)):
        return "must be three finite numbers [x, y, z] in metres"
    if value[2] <= 0.02:
        return "z must be more than 0.02 m in front of the camera"
    return None


_FINGER_POSE = ("sim.finger_identity", "sim.finger_roll_deg", "sim.finger_yaw_deg",
                "sim.finger_pitch_deg", "sim.finger_shift_mm")


def _finger_shift_problem(value: list[float]) -> str | None:
    if len(value) != 2 or not all(np.isfinite(value)) or max(abs(v) for v in value) > 5.0:
        return ("must be two finite numbers [dx, dy] in mm (the apex's shift in the image "
                "plane), each within +-5")
    return None


def _finger_config(node: Node) -> dict:
    """RigConfig fields of the simulated finger's identity and pose from sim.finger_*."""
    identity = int(node.get_parameter("sim.finger_identity").value)
    shift = [1e-3 * float(v) for v in node.get_parameter("sim.finger_shift_mm").value]
    x, y, z = RigConfig().finger_apex_optical_m
    return {
        "finger_identity": None if identity < 0 else identity,
        "finger_roll_deg": float(node.get_parameter("sim.finger_roll_deg").value),
        "finger_yaw_deg": float(node.get_parameter("sim.finger_yaw_deg").value),
        "finger_pitch_deg": float(node.get_parameter("sim.finger_pitch_deg").value),
        "finger_apex_optical_m": (x + shift[0], y + shift[1], z),
    }


def _array_value(node: Node, name: str) -> list:
    """An array parameter's value as a list of floats; [] when it is not set or empty."""
    return _numbers(node.get_parameter_or(name, Parameter(name, value=None)).value) or []


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


def _dynamic(desc: ParameterDescriptor) -> ParameterDescriptor:
    desc.dynamic_typing = True
    return desc


class DriverNode(Node):
    """Captures bursts on demand (service) or continuously (``rate`` > 0)."""

    def __init__(self) -> None:
        super().__init__("driver", namespace=topics.NAMESPACE)
        self._declare_parameters()
        # image_raw/compressed as image_transport publishes it; off by default (7 PNGs a
        # burst); encoded only while subscribed, after the burst is out
        self._image_compressed = CompressedTopics(
            self, topics.IMAGE_RAW, qos.SENSOR_QOS, self._checks, enabled_by_default=False)
        self._checks.refuse_unknown_overrides(self)

        self._lock = threading.Lock()
        self._counters = _Counters()
        self._burst_ms: collections.deque[float] = collections.deque(maxlen=TIMING_WINDOW)
        self._capture_rate = CaptureRate()
        self._publish_ms: collections.deque[float] = collections.deque(maxlen=TIMING_WINDOW)
        self._burst_id = 0
        self._emulator: BoardEmulator | None = None
        self._control: BoardEmulatorControl | None = None
        self._board: LedBoard | None = None
        self._camera: Camera | None = None
        self._rig: SimulatedRig | None = None
        self._sim_frame = 0  # frame index within the burst being captured (sim motion)
        self._sim_motion = (0.0, 0.0)  # the finger's motion over the burst being captured
        self._sim_steps = 1  # LED frames of that burst
        self._sim_moving_bursts = 0  # bursts that still move (sim.finger_motion_bursts)
        self._camera_info = CameraInfo()
        self._camera_info_manager: CameraInfoManager | None = None
        self._board_state = BoardState.DISCONNECTED
        self._firmware = ""
        self._reconnect_timer = None
        self._next_attempt = 0.0
        self._closed = False
        self._backoff = Backoff(float(self._param("reconnect_initial_s")),
                                max(float(self._param("reconnect_max_s")),
                                    float(self._param("reconnect_initial_s"))))
        try:
            self._open_hardware()
        except BaseException:
            self._close_hardware()
            raise

        self._pub_frames = self.create_publisher(TaggedFrame, topics.FRAMES, qos.SENSOR_QOS)
        self._pub_image = self.create_publisher(Image, topics.IMAGE_RAW, qos.SENSOR_QOS)
        self._pub_info = self.create_publisher(CameraInfo, topics.CAMERA_INFO, qos.SENSOR_QOS)
        self._pub_burst = self.create_publisher(Burst, topics.BURST, qos.BURST_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_service(CaptureBurst, topics.CAPTURE_BURST, self._on_capture)
        # camera_info_manager's service name, where camera_calibration's calibrator commits
        self.create_service(SetCameraInfo, "~/set_camera_info", self._on_set_camera_info)
        self.create_timer(1.0, self._on_diagnostics_timer)
        self._rate_timer = None
        self._apply_rate(self._param("rate"))
        self.add_post_set_parameters_callback(self._after_set)
        if self._board_state is not BoardState.CONNECTED:
            self._schedule_reconnect()
        assert self._camera is not None and self._board is not None
        self.get_logger().info(
            f"driver ready: board on {self._board.port} ({self._board_state.value}), "
            f"{self._led_count} LEDs, order {list(self._plan().led_order)}, camera "
            f"{self._param('camera')} {self._camera.width}x{self._camera.height} "
            f"{self._camera.encoding}")

    # ------------------------------------------------------------------ parameters
    def _param(self, name: str) -> object:
        return self.get_parameter(name).value

    @property
    def _led_count(self) -> int:
        return int(self._param("led_count"))

    def _declare_parameters(self) -> None:
        checks = self._checks = ParameterChecks(self)
        checks.add("camera", one_of(*(c.value for c in CameraBackend)))
        checks.add("camera_pixel_format", one_of("", "mono8", "mono16"))
        checks.add("camera_fourcc", lambda v: None if len(v) in (0, 4) and v.isascii()
                   else "must be four ASCII characters (e.g. GREY, YUYV, MJPG) or empty")
        checks.add("camera_width", lambda v: None if v >= 0 else "must be >= 0 (0 = default)")
        checks.add("camera_height", lambda v: None if v >= 0 else "must be >= 0 (0 = default)")
        checks.add("sim.scene", one_of(*(s.value for s in Scene)))
        checks.add("sim.reflectance", one_of(*(r.value for r in Reflectance)))
        checks.add("sim.bit_depth", lambda v: None if v in (8, 12) else "must be 8 or 12")
        checks.add("sim.sphere_center", _sphere_center_problem)
        checks.add("sim.finger_motion_px", lambda v: None if len(v) == 2 and all(
            np.isfinite(v)) and max(abs(x) for x in v) <= 100 else
            "must be two finite numbers [du, dv] in pixels, each within +-100")
        checks.add("sim.finger_identity", lambda v: None if -1 <= v <= 2**31 - 1 else
                   "must be -1 (the analytic spiral) or a fingerprint identity 0..2^31-1")
        checks.add("sim.finger_roll_deg", lambda v: None if abs(v) <= 45.0 else
                   "must be within +-45 degrees (beyond, the skin seen leaves the rolled print)")
        checks.add("sim.finger_yaw_deg", lambda v: None if abs(v) <= 90.0 else
                   "must be within +-90 degrees")
        checks.add("sim.finger_pitch_deg", lambda v: None if abs(v) <= 15.0 else
                   "must be within +-15 degrees (beyond, a margin comes near grazing)")
        checks.add("sim.finger_shift_mm", _finger_shift_problem)
        checks.add("led_order", lambda v: check_led_order(list(v), self._led_count))
        checks.add("exposure_times",
                   lambda v: _numbers_problem(v) or check_exposures(_numbers(v), self._led_count))
        checks.add("led_levels",
                   lambda v: _numbers_problem(v) or check_levels(_numbers(v), self._led_count))
        checks.add("reconnect_max_s", lambda v: None if v >= self._param("reconnect_initial_s")
                   else "must be >= reconnect_initial_s")
        p = self.declare_parameter
        # the board
        p("port", SIM_PORT, descriptor(
            "Serial device of the LED board (e.g. /dev/ttyACM0, or the emulator's --link), "
            "or 'sim' for the built-in board emulator on a pseudo-terminal", read_only=True))
        p("baudrate", 115200, descriptor("Serial baud rate", min_value=1200,
                                         max_value=4_000_000, integer=True, read_only=True))
        p("board_timeout", 0.05, descriptor(
            "Seconds one attempt waits for the board's reply", min_value=0.005, max_value=2.0,
            read_only=True))
        p("board_retries", 2, descriptor(
            "Resends of a command after a lost, late or corrupted reply", min_value=0,
            max_value=10, integer=True, read_only=True))
        p("wait_for_port", False, descriptor(
            "If the board is missing at start, wait and retry (with back-off) instead of "
            "exiting with code 2", read_only=True))
        p("reconnect_initial_s", 0.5, descriptor(
            "First delay before reopening a lost board, seconds; doubled per failed attempt",
            min_value=0.01, max_value=60.0, read_only=True))
        p("reconnect_max_s", 5.0, descriptor(
            "Longest delay between attempts to reopen a lost board, seconds",
            min_value=0.01, max_value=600.0, read_only=True))
        p("led_count", 7, descriptor("Number of LEDs on the board", min_value=3,
                                     max_value=16, integer=True, read_only=True))
        led_count = self._led_count
        p("led_order", list(range(led_count)), descriptor(
            "LEDs captured in a burst, in capture order (0-based, each at most once; default "
            "all in index order). Bursts are published sorted by LED index"))
        # exposure and levels
        p("exposure_time", 0.01, descriptor("Exposure time per frame, seconds",
                                            min_value=MIN_EXPOSURE_S, max_value=MAX_EXPOSURE_S))
        # Per-LED arrays default to [] with dynamic typing (the checks require numbers): a
        # statically typed parameter with no value makes rclpy's get_parameters service
        # answer nothing at all, so `ros2 param dump` printed {} (and rclpy types [] as bytes).
        p("exposure_times", [], _dynamic(descriptor(
            "Exposure time of each LED, seconds, indexed by LED (one per LED); "
            "empty: exposure_time for all")))
        p("led_level", 1.0, descriptor("Relative LED drive level, 0..1", min_value=0.0,
                                       max_value=1.0))
        p("led_levels", [], _dynamic(descriptor(
            "Relative drive level 0..1 of each LED, indexed by LED (one per LED); "
            "empty: led_level for all")))
        # capture modes
        p("rate", 0.0, descriptor(
            "Continuous capture rate in bursts per second; 0 = only on request",
            min_value=0.0, max_value=30.0))
        p("with_dark_frame", False, descriptor(
            "Add an all-LEDs-off frame to continuous bursts (ambient subtraction)"))
        # the camera
        p("camera", CameraBackend.SIM.value, descriptor(
            "Camera backend: 'sim' (the simulated rig), 'v4l2' (a real camera through "
            "OpenCV/V4L2) or 'folder' (replay of a DiLiGenT-layout image folder)",
            read_only=True))
        p("camera_device", "/dev/video0", descriptor(
            "v4l2: device path (e.g. /dev/video0 or /dev/v4l/by-id/...) or index",
            read_only=True))
        p("camera_folder", "", descriptor(
            "folder: the folder holding filenames.txt; the i-th listed image is LED i's",
            read_only=True))
        p("camera_width", 0, descriptor(
            "Image width to ask for (v4l2), to expect (folder) or to render (sim); 0 = the "
            "camera's", min_value=0, max_value=16384, integer=True, read_only=True))
        p("camera_height", 0, descriptor(
            "Image height, as camera_width", min_value=0, max_value=16384, integer=True,
            read_only=True))
        p("camera_pixel_format", "", descriptor(
            "mono8 or mono16; empty = the camera's (v4l2: mono8, folder: the images' bit "
            "depth, sim: sim.bit_depth)", read_only=True))
        p("camera_fourcc", "", descriptor(
            "v4l2: pixel format to ask for (GREY, YUYV, MJPG, 'Y16 '...); empty = mono8: "
            "the camera's default, mono16: 'Y16 '", read_only=True))
        p("camera_fps", 0.0, descriptor("v4l2: frame rate to ask for; 0 = the camera's",
                                         min_value=0.0, max_value=1000.0, read_only=True))
        p("camera_gain", -1.0, descriptor(
            "v4l2: gain in the device's units; negative = leave it as it is",
            min_value=-1.0, max_value=1e6, read_only=True))
        p("camera_discard_frames", 1, descriptor(
            "v4l2: frames dropped after each LED switch before the one kept (a free-running "
            "camera's frame in progress mixes two lights)", min_value=0, max_value=10,
            integer=True, read_only=True))
        p("camera_info_url", "", descriptor(
            "Where the camera's calibration is loaded from and set_camera_info stores it "
            "(camera_info_manager's rules): file:///path.yaml, package://pkg/path.yaml, "
            "${NAME} and ${ROS_HOME} substituted; empty = "
            f"{DEFAULT_CAMERA_INFO_URL}. Missing: the sim rig's true intrinsics, or none "
            "(K = 0) for the other cameras", read_only=True))
        p("camera_info_file", "", descriptor(
            "Older form of camera_info_url: a camera_info YAML path, which must exist and "
            "fit the camera (else exit 2); empty = use camera_info_url", read_only=True))
        p("frame_id", "fingerps_camera_optical_frame", descriptor(
            "TF frame of the camera's optical frame (REP-103)", read_only=True))
        p("camera_name", "fingerps_sim", descriptor(
            "Camera name: ${NAME} of camera_info_url, written into the calibration file "
            "(letters, digits, _)", read_only=True))
        # the simulated rig
        p("sim.scene", Scene.FINGER.value, descriptor(
            "What the simulated camera sees: finger, sphere, white_target or empty"))
        p("sim.reflectance", Reflectance.HK.value, descriptor(
            "Reflectance the simulated rig renders the finger with: hk or lambert",
            read_only=True))
        p("sim.bit_depth", 8, descriptor("Simulated sensor bit depth: 8 or 12",
                                         min_value=8, max_value=12, integer=True,
                                         read_only=True))
        p("sim.seed", 0, descriptor("Seed of the simulated sensor noise", min_value=0,
                                    integer=True, read_only=True))
        p("sim.sphere_center", list(RigConfig().sphere_center_optical_m), descriptor(
            "Where the simulated calibration sphere is, [x, y, z] metres in the optical "
            "frame; move it between calibrate_lights calls (add_placement) to estimate the "
            "LED positions"))
        p("sim.finger_motion_px", [0.0, 0.0], descriptor(
            "Simulated finger motion during a burst, [du, dv] pixels: frame i of n LEDs is "
            "shifted by i/n of it, the repeated first LED (repeat_first_led) by all of it"))
        p("sim.finger_motion_bursts", 0, descriptor(
            "Bursts the finger moves in once sim.finger_motion_px is set (counted from then); "
            "0 = every burst", min_value=0, max_value=1_000_000, integer=True))
        p("sim.finger_identity", -1, descriptor(
            "The simulated finger's fingerprint: -1 the analytic spiral, n >= 0 the synthetic "
            "fingerprint of identity n (SFinGe-style, ~1 s to generate); changing it or the "
            "pose rebuilds the finger (a few seconds) before the next burst",
            min_value=-1, max_value=2**31 - 1, integer=True))
        p("sim.finger_roll_deg", 0.0, descriptor(
            "Rotation of the simulated finger about its own axis, degrees (+ brings the skin "
            "at the apex towards +x)", min_value=-45.0, max_value=45.0))
        p("sim.finger_yaw_deg", 0.0, descriptor(
            "Rotation of the simulated finger about the optical axis through its apex, "
            "degrees, from +x towards +y (clockwise as displayed)",
            min_value=-90.0, max_value=90.0))
        p("sim.finger_pitch_deg", 0.0, descriptor(
            "Then its rotation about the optical x axis through its apex, degrees, from +y "
            "towards +z (+ brings the tip towards the camera)",
            min_value=-15.0, max_value=15.0))
        p("sim.finger_shift_mm", [0.0, 0.0], descriptor(
            "Shift [dx, dy] of the simulated finger's apex in the image plane, mm (optical "
            "x right, y down), each within +-5"))
        p("sim.board_control", "", descriptor(
            "Control socket of a board_emulator process (its --control): with a port other "
            "than 'sim', the sim and folder cameras see the LEDs that emulator has lit",
            read_only=True))

    def _plan(self) -> BurstPlan:
        return make_plan(
            led_count=self._led_count,
            led_order=list(self._param("led_order")),
            exposure_time=float(self._param("exposure_time")),
            exposure_times=_array_value(self, "exposure_times"),
            led_level=float(self._param("led_level")),
            led_levels=_array_value(self, "led_levels"))

    def _after_set(self, parameters: list) -> None:
        for param in parameters:
            if param.name == "rate":
                self._apply_rate(param.value)
            elif param.name in ("sim.finger_motion_px", "sim.finger_motion_bursts"):
                self._sim_moving_bursts = int(self._param("sim.finger_motion_bursts"))
            elif param.name == "sim.sphere_center" and self._rig is not None:
                with self._lock:  # not in the middle of a burst
                    self._rig = SimulatedRig(replace(
                        self._rig.config, sphere_center_optical_m=tuple(param.value)))
        if self._rig is not None and any(p.name in _FINGER_POSE for p in parameters):
            rig = SimulatedRig(replace(self._rig.config, **_finger_config(self)))
            if Scene(self._param("sim.scene")) is Scene.FINGER:
                rig.warm_up((Scene.FINGER,))  # outside the lock: bursts go on meanwhile
            with self._lock:
                self._rig = rig
            self.get_logger().info(f"sim finger: {_finger_config(self)}")

    def _apply_rate(self, rate: float) -> None:
        self._capture_rate.set_rate(rate, time.monotonic())
        if self._rate_timer is not None:
            self.destroy_timer(self._rate_timer)
            self._rate_timer = None
        if rate > 0:
            self._rate_timer = self.create_timer(1.0 / rate, self._on_rate_timer)

    # ------------------------------------------------------------------ set-up
    def _open_hardware(self) -> None:
        port = str(self._param("port"))
        if port == SIM_PORT:
            self._emulator = BoardEmulator(self._led_count)
            self._emulator.start()
            port = self._emulator.port
        control_path = str(self._param("sim.board_control"))
        if control_path:
            self._control = BoardEmulatorControl(control_path, timeout_s=1.0)
        self._board = LedBoard(port, baudrate=int(self._param("baudrate")),
                               timeout_s=float(self._param("board_timeout")),
                               retries=int(self._param("board_retries")))
        try:  # the board first: a missing port is the first thing to say
            self._connect_board()
            missing = None
        except BoardError as exc:
            if not self._param("wait_for_port") or isinstance(exc, _WrongBoardError):
                raise StartupError(
                    f"cannot use the LED board: {exc} (or use port:=sim for the simulated "
                    "rig, or wait_for_port:=true to wait for it)") from None
            missing = exc
        self._camera = self._make_camera()
        try:
            self._camera.open()
        except CameraError as exc:
            raise StartupError(f"cannot use the camera: {exc}") from None
        self._camera_info = self._make_camera_info()
        if isinstance(self._camera, OpenCvCamera) and self._camera.refused_settings:
            self.get_logger().warning(
                f"the camera refused {', '.join(self._camera.refused_settings)}; it runs with "
                "its own values there")
        if missing is not None:
            self._board_state = BoardState.WAITING
            self._counters.board_error = str(missing)
            self.get_logger().warning(f"waiting for the LED board on {port}: {missing}")

    def _connect_board(self) -> None:
        """Open the port, check the board, switch everything off; raises ``BoardError``."""
        board = self._board
        assert board is not None
        try:
            board.open()
            info = board.info()
            if info.led_count < self._led_count:
                raise _WrongBoardError(
                    f"the board on {board.port!r} has {info.led_count} LEDs but led_count is "
                    f"{self._led_count}; set led_count to at most {info.led_count}")
            board.all_off()
        except BoardError:
            board.close()
            raise
        self._firmware = info.firmware
        self._board_state = BoardState.CONNECTED
        self._counters.board_error = ""

    def _lit_source(self) -> object:
        """What the replaying cameras (sim, folder) ask for the LEDs lit now."""
        if self._control is not None:
            return self._control.lit_leds
        if self._emulator is not None:
            return self._emulator.lit_leds
        board = self._board

        def acknowledged() -> tuple[int, ...]:
            mask = board.acknowledged_mask if board is not None else None
            if mask is None:
                raise FingerpsDriverError("the board has acknowledged no switch yet")
            return mask_to_indices(mask)
        return acknowledged

    def _make_camera(self) -> Camera:
        backend = CameraBackend(self._param("camera"))
        width, height = int(self._param("camera_width")), int(self._param("camera_height"))
        if (width == 0) != (height == 0):
            raise StartupError("set camera_width and camera_height both, or neither")
        pixel_format = str(self._param("camera_pixel_format"))
        if backend is CameraBackend.SIM:
            return self._make_sim_camera(width, height, pixel_format)
        if backend is CameraBackend.FOLDER:
            folder = str(self._param("camera_folder"))
            if not folder:
                raise StartupError("camera:=folder needs camera_folder (a DiLiGenT-layout "
                                   "folder with filenames.txt)")
            return FolderCamera(folder, lit_leds=self._lit_source(), led_count=self._led_count,
                                width=width, height=height, encoding=pixel_format)
        plan = self._plan()
        return OpenCvCamera(
            parse_device(str(self._param("camera_device"))), width=width, height=height,
            fps=float(self._param("camera_fps")), exposure_s=plan.exposures_s[0],
            gain=float(self._param("camera_gain")), pixel_format=pixel_format or "mono8",
            fourcc=str(self._param("camera_fourcc")),
            discard_frames=int(self._param("camera_discard_frames")))

    def _make_sim_camera(self, width: int, height: int, pixel_format: str) -> Camera:
        bit_depth = int(self._param("sim.bit_depth"))
        encoding = "mono8" if bit_depth == 8 else "mono16"
        if pixel_format and pixel_format != encoding:
            raise StartupError(
                f"camera_pixel_format {pixel_format} does not match sim.bit_depth {bit_depth} "
                f"({encoding}); leave camera_pixel_format empty or change sim.bit_depth")
        size = {"width": width, "height": height} if width else {}
        try:
            config = RigConfig(reflectance=Reflectance(self._param("sim.reflectance")),
                               bit_depth=bit_depth, **size,
                               sphere_center_optical_m=tuple(self._param("sim.sphere_center")),
                               **_finger_config(self))
        except FingerpsDriverError as exc:
            raise StartupError(str(exc)) from None
        rig = self._rig = SimulatedRig(config)
        if rig.led_count != self._led_count:
            raise StartupError(
                f"the simulated rig has {rig.led_count} LEDs; set led_count to that")
        if self._emulator is None and self._control is None:
            raise StartupError(
                "camera:=sim needs port:=sim (the built-in board emulator) or, with a "
                "board_emulator process, sim.board_control:=<its --control socket>")
        rig.warm_up((Scene(self._param("sim.scene")),))  # the first burst is as fast as any
        rng = np.random.default_rng(int(self._param("sim.seed")))

        def render(lit: tuple[int, ...] | list[int]) -> np.ndarray:
            scene = Scene(self.get_parameter("sim.scene").value)
            step = min(self._sim_frame, self._sim_steps) / self._sim_steps
            self._sim_frame += 1
            du, dv = self._sim_motion
            return self._rig.render(scene, list(lit), rng=rng,
                                    finger_shift_px=(du * step, dv * step))

        return SimulatedCamera(render, self._lit_source(), width=config.width,
                               height=config.height, encoding=encoding)

    def _make_camera_info(self) -> CameraInfo:
        """Load the calibration (camera_info_url or camera_info_file) and say what is used."""
        assert self._camera is not None
        width, height = self._camera.width, self._camera.height
        url, legacy = str(self._param("camera_info_url")), str(self._param("camera_info_file"))
        if url and legacy:
            raise StartupError("set camera_info_url or camera_info_file, not both")
        fallback = None
        if self._rig is not None:
            fallback = CameraIntrinsics(width, height, self._rig.camera_matrix, "plumb_bob",
                                        np.zeros(5), str(self._param("camera_name")))
        try:
            manager = CameraInfoManager(
                camera_name=str(self._param("camera_name")),
                url=f"file://{os.path.abspath(legacy)}" if legacy else url,
                width=width, height=height, fallback=fallback,
                fallback_source="the simulated rig's true intrinsics", strict=bool(legacy))
            calibration = manager.load()
        except FingerpsCalibError as exc:
            raise StartupError(str(exc)) from None
        self._camera_info_manager = manager
        if calibration.problem is None:
            self.get_logger().info(f"camera calibration: {calibration.source}")
        elif calibration.intrinsics is not None and calibration.source == str(manager.path):
            self.get_logger().warning(calibration.problem)
        else:
            log = self.get_logger().info if fallback is not None and not url else \
                self.get_logger().warning
            log(f"{calibration.problem}: publishing {calibration.source}; to calibrate run "
                f"{self._how_to_calibrate()}")
        return intrinsics_to_camera_info(calibration.intrinsics, width=width, height=height)

    def _how_to_calibrate(self) -> str:
        node = self.get_fully_qualified_name()
        image = self.resolve_topic_name(topics.IMAGE_RAW)
        return (f"`ros2 run camera_calibration cameracalibrator --size COLSxROWS --square "
                f"METRES --ros-args -r image:={image} -r camera/set_camera_info:={node}/"
                "set_camera_info` (it stores the "
                "result through set_camera_info), or `ros2 run fingerps_calib calibrate_camera "
                "FOLDER --pattern COLSxROWS --square METRES --camera-name "
                f"{self._param('camera_name')} --camera-info-url "
                f"'{self._param('camera_info_url')}'`")

    def _on_set_camera_info(self, request: SetCameraInfo.Request,
                            response: SetCameraInfo.Response) -> SetCameraInfo.Response:
        """sensor_msgs/SetCameraInfo: validate, store to the URL's file, publish at once."""
        manager = self._camera_info_manager
        try:
            if manager is None:
                raise FingerpsCalibError("the camera is not open")
            intrinsics = camera_info_to_intrinsics(request.camera_info,
                                                   camera_name=manager.camera_name)
            calibration = manager.store(intrinsics)
        except FingerpsCalibError as exc:
            response.success = False
            response.status_message = f"calibration refused, nothing changed: {exc}"
            self.get_logger().warning(f"set_camera_info: {response.status_message}")
            return response
        except Exception as exc:  # answered, never raised into the executor
            response.success = False
            response.status_message = f"calibration not stored ({type(exc).__name__}: {exc})"
            self.get_logger().error(f"set_camera_info: {response.status_message}")
            return response
        self._camera_info = intrinsics_to_camera_info(
            calibration.intrinsics, width=manager.width, height=manager.height)
        info = self._stamped_camera_info(Header(stamp=self.get_clock().now().to_msg(),
                                                frame_id=str(self._param("frame_id"))))
        self._pub_info.publish(info)
        response.success = True
        response.status_message = f"stored in {calibration.source}"
        self.get_logger().info(f"set_camera_info: calibration in force, {response.status_message}")
        return response

    def _close_hardware(self) -> None:
        """LEDs off, then close the board, the camera and the emulator (each idempotent)."""
        if self._board is not None and self._board.is_open:
            try:
                self._board.all_off()
            except (FingerpsDriverError, OSError) as exc:
                self.get_logger().warning(f"could not switch the LEDs off: {exc}")
        if self._board is not None:
            self._board.close()
        if self._camera is not None:
            self._camera.close()
        if self._control is not None:
            self._control.close()
        if self._emulator is not None:
            self._emulator.stop()

    def destroy_node(self) -> None:
        """Switch the LEDs off and close the board and camera (idempotent)."""
        if not self._closed:
            self._closed = True
            with self._lock:
                self._close_hardware()
        super().destroy_node()

    # ------------------------------------------------------------------ board connection
    def _board_lost(self, reason: str) -> None:
        """The board vanished: close it, report it, start reconnecting."""
        assert self._board is not None
        self._board.close()
        self._board_state = BoardState.DISCONNECTED
        self._counters.disconnects += 1
        self._counters.board_error = reason
        self._counters.reconnect_attempts = 0
        self.get_logger().error(
            f"LED board on {self._board.port} lost: {reason}; reconnecting with back-off "
            f"({self._backoff.initial_s:g} s .. {self._backoff.max_s:g} s)")
        self._schedule_reconnect()
        self._publish_diagnostics()

    def _schedule_reconnect(self) -> None:
        if self._reconnect_timer is not None or self._closed:
            return
        delay = self._backoff.delay_s(self._counters.reconnect_attempts)
        self._next_attempt = time.monotonic() + delay
        self._reconnect_timer = self.create_timer(delay, self._try_reconnect)

    def _try_reconnect(self) -> None:
        if self._reconnect_timer is not None:
            self.destroy_timer(self._reconnect_timer)
            self._reconnect_timer = None
        if self._closed or self._board_state is BoardState.CONNECTED:
            return
        self._counters.reconnect_attempts += 1
        with self._lock:
            try:
                self._connect_board()
            except BoardError as exc:
                self._counters.board_error = str(exc)
                self.get_logger().warning(
                    f"LED board still unavailable (attempt "
                    f"{self._counters.reconnect_attempts}): {exc}", throttle_duration_sec=10.0)
                self._schedule_reconnect()
                return
        self._counters.reconnects += 1
        assert self._board is not None
        self.get_logger().info(
            f"LED board on {self._board.port} connected ({self._firmware}) after "
            f"{self._counters.reconnect_attempts} attempt(s)")
        self._counters.reconnect_attempts = 0
        self._publish_diagnostics()

    def _port_vanished(self) -> bool:
        """True if the connected board's device node is gone (USB unplugged, link removed)."""
        assert self._board is not None
        return (self._board_state is BoardState.CONNECTED
                and not os.path.exists(self._board.port))

    # ------------------------------------------------------------------ capture
    def _on_rate_timer(self) -> None:
        if self._board_state is not BoardState.CONNECTED:
            return  # reported in the diagnostics; requests would only fail
        result, _ = self.capture(with_dark=bool(self._param("with_dark_frame")))
        if result.ok:
            self._capture_rate.captured(time.monotonic())

    def _on_capture(self, request: CaptureBurst.Request,
                    response: CaptureBurst.Response) -> CaptureBurst.Response:
        result, burst = self.capture(with_dark=request.with_dark_frame,
                                     publish=not request.response_only,
                                     repeat_first=request.repeat_first_led)
        response.success = result.ok
        response.message = "ok" if result.ok else result.reason
        if burst is not None:
            response.burst = burst
        return response

    def capture(self, *, with_dark: bool, publish: bool = True, repeat_first: bool = False
                ) -> tuple[BurstResult, Burst | None]:
        """Capture one burst, publish it if asked; return the result and the message if whole.

        A failed burst is counted, logged and never published.
        """
        with self._lock:
            if self._closed or self._board is None or self._camera is None:
                raise FingerpsDriverError("the driver is shutting down")
            if self._board_state is not BoardState.CONNECTED:
                result = self._refused(self._not_connected_reason())
            else:
                self._burst_id += 1
                plan = self._plan()
                self._start_sim_motion(len(plan.led_order))
                result = capture_burst(
                    self._board, self._camera, burst_id=self._burst_id,
                    led_order=plan.led_order, exposures_s=plan.exposures_s,
                    levels=plan.levels, with_dark=with_dark, repeat_first=repeat_first,
                    expected_shape=(self._camera.height, self._camera.width))
        if not result.ok:
            self._burst_failed(result)
            return result, None
        c = self._counters
        c.ok += 1
        c.last_burst_failed = False
        c.last_burst_ms = result.duration_s * 1e3
        self._burst_ms.append(c.last_burst_ms)
        return result, self._publish(result, publish=publish)

    def _start_sim_motion(self, steps: int) -> None:
        """Set the simulated finger's motion for the burst about to be captured."""
        if self._rig is None:
            return
        motion = tuple(float(v) for v in self._param("sim.finger_motion_px"))
        moving = any(motion) and (int(self._param("sim.finger_motion_bursts")) == 0
                                  or self._sim_moving_bursts > 0)
        if moving and self._sim_moving_bursts > 0:
            self._sim_moving_bursts -= 1
        self._sim_motion = motion if moving else (0.0, 0.0)
        self._sim_frame, self._sim_steps = 0, max(steps, 1)

    def _not_connected_reason(self) -> str:
        assert self._board is not None
        wait = max(0.0, self._next_attempt - time.monotonic())
        state = ("is not there yet" if self._board_state is BoardState.WAITING
                 else "is disconnected")
        return (f"no burst: the LED board on {self._board.port} {state} "
                f"({self._counters.board_error}); reconnecting, next attempt in {wait:.1f} s")

    def _refused(self, reason: str) -> BurstResult:
        return BurstResult(0, (), None, False, reason, 0.0, failed_step="board",
                           error_type="BoardDisconnectedError")

    def _burst_failed(self, result: BurstResult) -> None:
        c = self._counters
        c.failed += 1
        c.last_error = result.reason
        c.last_burst_failed = True
        if result.camera_failed:
            c.camera_error = result.reason
        self.get_logger().warning(result.reason, throttle_duration_sec=1.0)
        board = self._board
        if (board is not None and self._board_state is BoardState.CONNECTED
                and not board.is_open):
            self._board_lost(result.reason)
        elif result.error_type == BoardRejectedError.__name__:
            self.get_logger().error("the board rejected a command: check led_count and "
                                    "led_order against the board", throttle_duration_sec=10.0)

    def _tagged(self, frame: CapturedFrame, burst_id: int, header_frame: str) -> TaggedFrame:
        assert self._camera is not None
        header = Header(stamp=_stamp(frame.stamp_ns), frame_id=header_frame)
        return TaggedFrame(
            header=header, burst_id=burst_id, led_index=frame.led_index,
            led_count=self._led_count, exposure_time=frame.exposure_s,
            led_intensity=frame.level,
            image=array_to_image(frame.image, encoding=self._camera.encoding, header=header))

    def _publish(self, result: BurstResult, *, publish: bool) -> Burst:
        """Build the messages (and publish them); the time it takes is ``publish_ms``."""
        start = time.perf_counter()
        frame_id = str(self._param("frame_id"))
        tagged = [self._tagged(f, result.burst_id, frame_id) for f in result.frames]
        if publish:
            for msg in tagged:  # in capture order, as they were taken
                self._pub_frames.publish(msg)
                self._pub_image.publish(msg.image)
        last = tagged[-1].header
        info = self._stamped_camera_info(last)
        by_led = sorted(tagged, key=lambda f: f.led_index)  # Burst.msg: frames in LED order
        burst = Burst(header=last, burst_id=result.burst_id, frames=by_led, camera_info=info)
        if result.dark is not None:
            burst.has_dark_frame = True
            burst.dark_frame = self._tagged(result.dark, result.burst_id, frame_id)
        if result.repeat is not None:
            burst.has_repeat_frame = True
            burst.repeat_frame = self._tagged(result.repeat, result.burst_id, frame_id)
        if publish:
            self._pub_info.publish(info)
            self._pub_burst.publish(burst)
            self._counters.last_publish_ms = (time.perf_counter() - start) * 1e3
            self._publish_ms.append(self._counters.last_publish_ms)
            for msg, frame in zip(tagged, result.frames, strict=True):
                self._image_compressed.publish(frame.image, msg.image.encoding, msg.header)
        return burst

    # ------------------------------------------------------------------ diagnostics
    def _stamped_camera_info(self, header: Header) -> CameraInfo:
        current = self._camera_info  # replaced whole by set_camera_info, never modified
        return CameraInfo(header=header, width=current.width, height=current.height,
                          distortion_model=current.distortion_model, d=current.d,
                          k=current.k, r=current.r, p=current.p)

    def _on_diagnostics_timer(self) -> None:
        if self._port_vanished():
            assert self._board is not None
            self._board_lost(f"port {self._board.port} vanished")  # publishes diagnostics
            return
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        array = DiagnosticArray(status=[self._board_status(), self._camera_status(),
                                        self._burst_status()])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)

    def _board_status(self) -> DiagnosticStatus:
        assert self._board is not None
        c, state = self._counters, self._board_state
        status = DiagnosticStatus(name=f"{self.get_name()}: board",
                                  hardware_id=self._board.port)
        if state is BoardState.CONNECTED:
            status.level = DiagnosticStatus.OK
            status.message = f"connected ({self._firmware})"
        else:
            status.level = (DiagnosticStatus.ERROR if state is BoardState.DISCONNECTED
                            else DiagnosticStatus.WARN)
            wait = max(0.0, self._next_attempt - time.monotonic())
            status.message = (f"{state.value}: {c.board_error}; next attempt in "
                              f"{wait:.1f} s")
        status.values = [
            KeyValue(key="state", value=state.value),
            KeyValue(key="port", value=self._board.port),
            KeyValue(key="firmware", value=self._firmware),
            KeyValue(key="resends", value=str(self._board.resends)),
            KeyValue(key="disconnects", value=str(c.disconnects)),
            KeyValue(key="reconnects", value=str(c.reconnects)),
            KeyValue(key="reconnect_attempts", value=str(c.reconnect_attempts)),
            KeyValue(key="last_board_error", value=c.board_error),
        ]
        return status

    def _camera_status(self) -> DiagnosticStatus:
        camera = self._camera
        assert camera is not None
        backend = str(self._param("camera"))
        device = {CameraBackend.V4L2.value: str(self._param("camera_device")),
                  CameraBackend.FOLDER.value: str(self._param("camera_folder"))}.get(backend, "")
        status = DiagnosticStatus(name=f"{self.get_name()}: camera",
                                  hardware_id=device or backend)
        c = self._counters
        camera_failed_last = c.last_burst_failed and c.camera_error == c.last_error
        status.level = DiagnosticStatus.WARN if camera_failed_last else DiagnosticStatus.OK
        status.message = (f"last burst failed at the camera: {c.camera_error}"
                          if camera_failed_last else "ok")
        refused = getattr(camera, "refused_settings", [])
        status.values = [
            KeyValue(key="backend", value=backend),
            KeyValue(key="device", value=device),
            KeyValue(key="size", value=f"{camera.width}x{camera.height}"),
            KeyValue(key="encoding", value=camera.encoding),
            KeyValue(key="frames", value=str(getattr(camera, "frames_grabbed", ""))),
            KeyValue(key="refused_settings", value=", ".join(refused)),
            KeyValue(key="compressed_failures", value=str(self._image_compressed.failures)),
            KeyValue(key="calibration", value=(self._camera_info_manager.current.source
                                               if self._camera_info_manager else "")),
            KeyValue(key="last_camera_error", value=c.camera_error),
        ]
        return status

    def _burst_status(self) -> DiagnosticStatus:
        c = self._counters
        status = DiagnosticStatus(name=f"{self.get_name()}: bursts",
                                  hardware_id=str(self._param("port")))
        status.level = DiagnosticStatus.WARN if c.last_burst_failed else DiagnosticStatus.OK
        status.message = f"last burst failed: {c.last_error}" if c.last_burst_failed else "ok"
        rate = self._capture_rate.report(time.monotonic())
        if rate.behind and not c.last_burst_failed:
            status.level = DiagnosticStatus.WARN
            status.message = (
                f"continuous capture delivers {rate.achieved:.1f} bursts/s of the "
                f"{rate.requested:g} asked for: a burst takes longer than 1/rate (see "
                "burst_ms_median and publish_ms_median); lower rate")

        def stats(values: collections.deque[float]) -> tuple[str, str]:
            if not values:
                return "", ""
            return f"{statistics.median(values):.2f}", f"{max(values):.2f}"

        burst_median, burst_max = stats(self._burst_ms)
        publish_median, publish_max = stats(self._publish_ms)
        status.values = [
            KeyValue(key="bursts_ok", value=str(c.ok)),
            KeyValue(key="bursts_failed", value=str(c.failed)),
            KeyValue(key="last_error", value=c.last_error),
            KeyValue(key="last_burst_ms", value=f"{c.last_burst_ms:.1f}"),
            KeyValue(key="burst_ms_median", value=burst_median),
            KeyValue(key="burst_ms_max", value=burst_max),
            KeyValue(key="last_publish_ms", value=f"{c.last_publish_ms:.2f}"),
            KeyValue(key="publish_ms_median", value=publish_median),
            KeyValue(key="publish_ms_max", value=publish_max),
            KeyValue(key="timing_window", value=str(len(self._publish_ms))),
            KeyValue(key="rate_requested", value=f"{rate.requested:g}"),
            KeyValue(key="rate_achieved",
                     value="" if rate.achieved is None else f"{rate.achieved:.2f}"),
        ]
        return status


class _WrongBoardError(BoardError):
    """The board answers but does not fit the configuration (too few LEDs)."""


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_driver driver_node``."""
    return run_node(DriverNode, args=args, name="driver_node",
                    expected_errors=(FingerpsDriverError,))


if __name__ == "__main__":
    raise SystemExit(main())
