"""The camera the driver's parameters ask for, and the calibration it publishes.

No ROS here: driver_node reads its parameters into ``CameraSettings``; ``make_camera`` makes
a v4l2 camera (OpenCV), a folder replay, or the simulated rig's camera, which renders what
the board has lit through a ``RigRenderer`` (the scene shown, the finger's motion over a
burst); ``open_calibration`` loads the camera's calibration by camera_info_manager's rules
and says in the log what is published.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics
from fingerps_driver.board.board_protocol import LED_COUNT
from fingerps_driver.cameras.camera import Camera, SimulatedCamera
from fingerps_driver.cameras.camera_folder import FolderCamera
from fingerps_driver.cameras.camera_info_manager import CameraInfoManager
from fingerps_driver.cameras.camera_opencv import OpenCvCamera, parse_device
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import (
    FingertipShape,
    MirrorSphere,
    PinholeCamera,
    Reflectance,
    RigConfig,
    Scene,
    SensorModel,
    SimulatedRig,
    SkinReflectance,
)
from fingerps_ros.log import Log

FALLBACK_SOURCE = "the simulated rig's true intrinsics"
_RIG = RigConfig()


class CameraBackend(Enum):
    """The ``camera`` parameter."""

    SIM = "sim"
    V4L2 = "v4l2"
    FOLDER = "folder"


@dataclass(frozen=True)
class SimSettings:
    """The simulated rig's parameters (``sim.*``).

    ``finger`` holds the ``FingertipShape`` fields of the finger's identity and pose;
    ``motion_px`` and ``motion_bursts`` the finger's motion during a burst (see
    ``RigRenderer``).
    """

    scene: Scene = Scene.FINGER
    reflectance: Reflectance = _RIG.skin.model
    bit_depth: int = _RIG.sensor.bit_depth
    seed: int = 0
    sphere_center_optical_m: tuple[float, ...] = _RIG.sphere.center_optical_m
    finger: Mapping[str, Any] = field(default_factory=dict)
    motion_px: tuple[float, float] = (0.0, 0.0)
    motion_bursts: int = 0

    @property
    def encoding(self) -> str:
        """The simulated camera's pixel format, by ``bit_depth``."""
        return "mono8" if self.bit_depth == 8 else "mono16"


@dataclass(frozen=True)
class CameraSettings:
    """The camera's parameters (``camera*``, ``sim.*``); see the driver's parameter table.

    ``exposure_s`` is the exposure a v4l2 camera starts with (the burst's first LED's).
    """

    backend: CameraBackend = CameraBackend.SIM
    device: str = "/dev/video0"
    folder: str = ""
    width: int = 0
    height: int = 0
    pixel_format: str = ""
    fourcc: str = ""
    fps: float = 0.0
    gain: float = -1.0
    discard_frames: int = 1
    exposure_s: float = 0.01
    led_count: int = LED_COUNT
    camera_name: str = "fingerps_sim"
    camera_info_url: str = ""
    camera_info_file: str = ""
    sim: SimSettings = field(default_factory=SimSettings)

    @property
    def device_name(self) -> str:
        """The device (v4l2) or folder (folder) the camera reads; empty for sim."""
        return {CameraBackend.V4L2: self.device,
                CameraBackend.FOLDER: self.folder}.get(self.backend, "")


class RigRenderer:
    """Renders the simulated rig for the sim camera: the scene shown and the finger's
    motion over the burst being captured.

    Frame i of a burst of n LED frames shows the finger shifted by i/n of ``motion_px``,
    the repeated first LED by all of it. With ``motion_bursts`` > 0 the finger moves only
    in that many bursts after each ``set_motion``; 0: in every burst.
    """

    def __init__(self, rig: SimulatedRig, settings: SimSettings) -> None:
        self.rig = rig
        self.scene = settings.scene
        self._rng = np.random.default_rng(settings.seed)
        self._motion_px = settings.motion_px
        self._motion_bursts = settings.motion_bursts
        self._moving_bursts = 0  # bursts that still move (counted from set_motion)
        self._motion = (0.0, 0.0)  # the finger's motion over the burst being captured
        self._frame = 0  # frame index within that burst
        self._steps = 1  # its LED frames

    def set_motion(self, motion_px: Sequence[float], motion_bursts: int) -> None:
        """New ``sim.finger_motion_px``/``sim.finger_motion_bursts``, counted from now."""
        self._motion_px = (float(motion_px[0]), float(motion_px[1]))
        self._motion_bursts = self._moving_bursts = int(motion_bursts)

    def start_burst(self, steps: int) -> None:
        """Set the finger's motion for the burst of ``steps`` LED frames about to start."""
        motion = self._motion_px
        moving = any(motion) and (self._motion_bursts == 0 or self._moving_bursts > 0)
        if moving and self._moving_bursts > 0:
            self._moving_bursts -= 1
        self._motion = motion if moving else (0.0, 0.0)
        self._frame, self._steps = 0, max(steps, 1)

    def render(self, lit: Sequence[int]) -> np.ndarray:
        """The next frame of the burst with the LEDs ``lit``."""
        step = min(self._frame, self._steps) / self._steps
        self._frame += 1
        du, dv = self._motion
        return self.rig.render(self.scene, list(lit), rng=self._rng,
                               finger_shift_px=(du * step, dv * step))

    def moved_sphere(self, center: Sequence[float]) -> SimulatedRig:
        """The rig with the calibration sphere at ``center`` (metres, optical frame)."""
        config = self.rig.config
        return SimulatedRig(replace(
            config, sphere=replace(config.sphere, center_optical_m=tuple(center))))

    def posed_finger(self, finger: Mapping[str, Any]) -> SimulatedRig:
        """The rig with the finger of ``finger`` (``FingertipShape`` fields), warmed up if
        shown."""
        config = self.rig.config
        rig = SimulatedRig(replace(config, finger=replace(config.finger, **finger)))
        if self.scene is Scene.FINGER:
            rig.warm_up((Scene.FINGER,))
        return rig


def make_camera(settings: CameraSettings, lit_leds: Callable[[], Sequence[int]], *,
                emulated: bool) -> tuple[Camera, RigRenderer | None]:
    """The camera of ``settings`` (not open yet), and the renderer of a sim camera.

    ``lit_leds`` tells the replaying cameras (sim, folder) which LEDs are lit;
    ``emulated``: an emulator shows them (the sim camera needs one).

    Raises
    ------
    FingerpsDriverError
        Settings that do not fit together, one line saying what to change.
    """
    width, height = settings.width, settings.height
    if (width == 0) != (height == 0):
        raise FingerpsDriverError("set camera_width and camera_height both, or neither")
    if settings.backend is CameraBackend.SIM:
        renderer = _make_renderer(settings, emulated=emulated)
        config = renderer.rig.config
        camera = SimulatedCamera(renderer.render, lit_leds, width=config.camera.width,
                                 height=config.camera.height, encoding=settings.sim.encoding)
        return camera, renderer
    if settings.backend is CameraBackend.FOLDER:
        if not settings.folder:
            raise FingerpsDriverError("camera:=folder needs camera_folder (a DiLiGenT-layout "
                                      "folder with filenames.txt)")
        return FolderCamera(settings.folder, lit_leds=lit_leds, led_count=settings.led_count,
                            width=width, height=height, encoding=settings.pixel_format), None
    return OpenCvCamera(
        parse_device(settings.device), width=width, height=height, fps=settings.fps,
        exposure_s=settings.exposure_s, gain=settings.gain,
        pixel_format=settings.pixel_format or "mono8", fourcc=settings.fourcc,
        discard_frames=settings.discard_frames), None


def _make_renderer(settings: CameraSettings, *, emulated: bool) -> RigRenderer:
    sim = settings.sim
    encoding = sim.encoding
    if settings.pixel_format and settings.pixel_format != encoding:
        raise FingerpsDriverError(
            f"camera_pixel_format {settings.pixel_format} does not match sim.bit_depth "
            f"{sim.bit_depth} ({encoding}); leave camera_pixel_format empty or change "
            "sim.bit_depth")
    size = {"width": settings.width, "height": settings.height} if settings.width else {}
    config = RigConfig(camera=PinholeCamera(**size), sensor=SensorModel(bit_depth=sim.bit_depth),
                       skin=SkinReflectance(model=sim.reflectance),
                       finger=FingertipShape(**sim.finger),
                       sphere=MirrorSphere(center_optical_m=tuple(sim.sphere_center_optical_m)))
    rig = SimulatedRig(config)
    if rig.led_count != settings.led_count:
        raise FingerpsDriverError(
            f"the simulated rig has {rig.led_count} LEDs; set led_count to that")
    if not emulated:
        raise FingerpsDriverError(
            "camera:=sim needs port:=sim (the built-in board emulator) or, with a "
            "board_emulator process, sim.board_control:=<its --control socket>")
    rig.warm_up((sim.scene,))  # the first burst is as fast as any
    return RigRenderer(rig, sim)


def open_calibration(settings: CameraSettings, camera: Camera, rig: SimulatedRig | None, *,
                     node_name: str, image_topic: str, log: Log) -> CameraInfoManager:
    """Load the calibration (camera_info_url or camera_info_file) and say what is used.

    ``rig``'s true intrinsics are the fallback of a sim camera; ``node_name`` and
    ``image_topic`` go into the line saying how to calibrate.

    Raises
    ------
    FingerpsDriverError
        Both URL and file set, a bad URL or camera name, or (``camera_info_file``) a
        missing or unfitting file.
    """
    width, height = camera.width, camera.height
    url, legacy = settings.camera_info_url, settings.camera_info_file
    if url and legacy:
        raise FingerpsDriverError("set camera_info_url or camera_info_file, not both")
    fallback = None
    if rig is not None:
        fallback = CameraIntrinsics(width, height, rig.camera_matrix, "plumb_bob",
                                    np.zeros(5), settings.camera_name)
    try:
        manager = CameraInfoManager(
            camera_name=settings.camera_name,
            url=f"file://{os.path.abspath(legacy)}" if legacy else url,
            width=width, height=height, fallback=fallback, fallback_source=FALLBACK_SOURCE,
            strict=bool(legacy))
        calibration = manager.load()
    except FingerpsCalibError as exc:
        raise FingerpsDriverError(str(exc)) from None
    if calibration.problem is None:
        log.info(f"camera calibration: {calibration.source}")
    elif calibration.intrinsics is not None and calibration.source == str(manager.path):
        log.warning(calibration.problem)
    else:
        say = log.info if fallback is not None and not url else log.warning
        say(f"{calibration.problem}: publishing {calibration.source}; to calibrate run "
            f"{how_to_calibrate(settings, node_name=node_name, image_topic=image_topic)}")
    return manager


def how_to_calibrate(settings: CameraSettings, *, node_name: str, image_topic: str) -> str:
    """The two commands that calibrate the camera and store the result where it is read."""
    return (f"`ros2 run camera_calibration cameracalibrator --size COLSxROWS --square "
            f"METRES --ros-args -r image:={image_topic} -r camera/set_camera_info:={node_name}/"
            "set_camera_info` (it stores the "
            "result through set_camera_info), or `ros2 run fingerps_calib calibrate_camera "
            "FOLDER --pattern COLSxROWS --square METRES --camera-name "
            f"{settings.camera_name} --camera-info-url "
            f"'{settings.camera_info_url}'`")
