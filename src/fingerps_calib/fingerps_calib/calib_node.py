"""calib_node: light directions from a shiny sphere and flat-field maps from a white target.

Thin ROS adapter around ``fingerps_calib.lights.sphere_calibration.calibrate_lights``,
``fingerps_calib.lights.led_triangulation.combine_placements`` and
``fingerps_calib.flat_field_calibration.flat_field_maps``. The services take the images in
the request, or, when the request has none, ask the driver for a burst. Camera intrinsics
come from ``camera_info_file`` when it is set, else from the driver's camera_info.

A light calibration with ``add_placement`` is combined with the placements of the
calibration in force (two or more: the LED positions are triangulated); without it, the new
placement alone is the calibration (and starts a new set of placements).

A calibration that fails its checks is not published, not saved, and the last good one stays
in force (its picture is saved as ``*_rejected.png``). A good one is published reliable and
transient-local (nodes that start later still receive it), saved to ``calibration_dir``
(``fingerps_calib.calibration_store``) with its picture (``calibration_picture``), and loaded
from there at the next start.

Every service call is answered: bad input (a sphere radius outside 0.5-50 mm, frames
smaller than 64x64 or not of the camera's size, a calibration that is not finite or is
degenerate) gets ``success: false`` and a reason, and an unexpected error in a callback is
logged in one line and answered the same way; the node keeps serving. ``/diagnostics``
counts the calls answered ok, refused and failed unexpectedly, with the last error (level
WARN while the latest call was refused, ERROR if it failed unexpectedly).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Vector3
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_calib.calibration_picture import (
    distort_points,
    flat_field_picture,
    lights_picture,
    sphere_outline,
    write_png,
)
from fingerps_calib.calibration_store import (
    FLAT_FIELD_FILE,
    LIGHTS_FILE,
    FlatFieldRecord,
    LightsRecord,
    flat_field_problems,
    iso_date,
    lights_problems,
    load_flat_field,
    load_lights,
    save_flat_field,
    save_lights,
)
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import MIN_IMAGE_SIDE_PX, flat_field_maps
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, load_camera_info
from fingerps_calib.lights.led_triangulation import Placement, combine_placements
from fingerps_calib.lights.sphere_calibration import (
    RADIUS_RANGE_M,
    LightCalibrationResult,
    calibrate_lights,
    check_radius,
)
from fingerps_msgs.msg import FlatField, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights, CaptureBurst
from fingerps_ros import qos, topics
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image, image_to_array
from fingerps_ros.node_runner import StartupError, run_node
from fingerps_ros.parameters import ParameterChecks, descriptor

DEFAULT_FRAME_ID = "fingerps_camera_optical_frame"
LIGHTS_PICTURE = "lights.png"
FLAT_FIELD_PICTURE = "flat_field.png"


def default_calibration_dir() -> str:
    """``$ROS_HOME/fingerps/calibration`` (ROS_HOME defaults to ~/.ros)."""
    ros_home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    return os.path.join(ros_home, "fingerps", "calibration")


@dataclass(frozen=True)
class _Camera:
    """The intrinsics a calibration uses and where they came from."""

    matrix: np.ndarray
    distortion: np.ndarray | None
    width: int
    height: int
    source: str


class CalibNode(Node):
    """Serves the calibration services and publishes the calibration in force."""

    def __init__(self) -> None:
        super().__init__("calib", namespace=topics.NAMESPACE)
        self._checks = ParameterChecks(self)
        p = self.declare_parameter
        p("sphere_radius", 0.004, descriptor(
            "Radius of the calibration sphere, metres (used when a request gives 0); "
            "0.0005-0.05 (a sphere seen whole by the camera, its silhouette wide enough to fit)",
            min_value=RADIUS_RANGE_M[0], max_value=RADIUS_RANGE_M[1]))
        p("capture_timeout", 5.0, descriptor(
            "Seconds to wait for the driver's burst when a request carries no images",
            min_value=0.1, max_value=60.0))
        p("flat_field_degree", 4, descriptor(
            "Degree of the smooth 2D polynomial fitted to each white-target image (so paper "
            "texture and noise do not enter the flat-field maps)", min_value=1, max_value=10,
            integer=True))
        p("camera_name", "fingerps_sim", descriptor(
            "Camera name written into calibrations; a saved calibration of another camera "
            "is not loaded", constraints="not empty"))
        p("calibration_dir", default_calibration_dir(), descriptor(
            "Directory where the calibration in force is saved (lights.yaml, "
            "flat_field.yaml + .npz, pictures) and loaded from at start; empty: neither",
            read_only=True))
        p("camera_info_file", "", descriptor(
            "camera_info YAML (camera_calibration format) with the intrinsics; empty: use the "
            "driver's camera_info", read_only=True))
        p("reference_point", [0.0, 0.0025, 0.09], descriptor(
            "Point (x, y, z) in metres, optical frame, where the finger rests (the default: "
            "the simulated rig's fingertip apex); the directions of a calibration from two "
            "or more sphere placements start there, and its distance is the expected "
            "distance of the sphere", constraints="three finite numbers, z > 0"))
        p("sphere_distance_tolerance", 0.3, descriptor(
            "The sphere centre must lie within this fraction of the reference point's "
            "distance from the camera (a wrong sphere radius shows as a wrong distance)",
            min_value=0.05, max_value=0.9))
        p("mono16_full_scale", 4095.0, descriptor(
            "Largest value of a mono16 image (4095 for 12-bit sensors)", min_value=1.0,
            max_value=65535.0))
        self._checks.add("reference_point", _check_reference_point)
        self._checks.add("camera_name", _check_camera_name)
        self._checks.add("sphere_radius", _check_sphere_radius)
        for name in ("capture_timeout", "sphere_distance_tolerance", "mono16_full_scale"):
            self._checks.add(name, _check_finite)
        self._checks.refuse_unknown_overrides(self)
        problems = self._checks.problems(
            [self.get_parameter(name) for name in (
                "reference_point", "camera_name", "sphere_radius", "capture_timeout",
                "sphere_distance_tolerance", "mono16_full_scale")])
        if problems:
            raise StartupError("; ".join(problems))

        self._file_camera: CameraIntrinsics | None = None
        info_file = str(self.get_parameter("camera_info_file").value)
        if info_file:
            self._file_camera = load_camera_info(info_file)  # FingerpsCalibError: exit 2
        directory = str(self.get_parameter("calibration_dir").value)
        self._dir = Path(directory).expanduser() if directory else None
        if self._dir is not None:
            try:
                self._dir.mkdir(parents=True, exist_ok=True)
                writable = os.access(self._dir, os.W_OK)
            except OSError as exc:
                writable, reason = False, str(exc)
            else:
                reason = "not writable"
            if not writable:
                raise StartupError(
                    f"calibration_dir {self._dir}: {reason}; set calibration_dir to a "
                    "writable directory (or to '' to neither save nor load calibrations)")

        self._service_group = MutuallyExclusiveCallbackGroup()
        self._client_group = ReentrantCallbackGroup()
        self._capture = self.create_client(CaptureBurst, topics.CAPTURE_BURST,
                                           callback_group=self._client_group)
        self._camera_info: CameraInfo | None = None
        self.create_subscription(CameraInfo, topics.CAMERA_INFO, self._on_camera_info,
                                 qos.SENSOR_QOS, callback_group=self._client_group)
        self._pub_lights = self.create_publisher(LightCalibration, topics.LIGHT_CALIBRATION,
                                                 qos.CALIBRATION_QOS)
        self._pub_flat = self.create_publisher(FlatField, topics.FLAT_FIELD,
                                               qos.CALIBRATION_QOS)
        self._lights: LightsRecord | None = None
        self._flat: FlatFieldRecord | None = None
        self._lights_msg: LightCalibration | None = None
        self._calls = _Calls()
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._load_saved()
        self.create_service(CalibrateLights, topics.CALIBRATE_LIGHTS,
                            self._answering("calibrate_lights", self._on_lights),
                            callback_group=self._service_group)
        self.create_service(CalibrateFlatField, topics.CALIBRATE_FLAT_FIELD,
                            self._answering("calibrate_flat_field", self._on_flat),
                            callback_group=self._service_group)
        self.create_timer(1.0, self._publish_diagnostics)
        source = f"camera_info_file {info_file}" if info_file else "the driver's camera_info"
        where = str(self._dir) if self._dir is not None else "nowhere (calibration_dir empty)"
        self.get_logger().info(f"calib ready: intrinsics from {source}; calibrations saved "
                               f"to {where}")

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self._camera_info = msg

    # ------------------------------------------------------------------ answers, diagnostics
    def _answering(self, service: str, handler: Callable) -> Callable:
        """``handler`` as a service callback that always answers: an unexpected exception is
        logged in one line, counted, and answered with success false and its reason."""
        def callback(request, response):
            try:
                answer = handler(request, response)
            except Exception as exc:  # every call gets an answer
                text = _one_line(f"{type(exc).__name__}: {exc}")
                answer = type(response)()
                answer.success = False
                answer.message = (
                    f"{service} failed unexpectedly ({text}); {self._in_force()}; check the "
                    "request's frames and calib_node's parameters, and report this error "
                    "with calib_node's log if they are right")
                self.get_logger().error(f"{service}: unexpected error, answered with "
                                        f"success false: {text}")
                self._calls.count(service, answer.message, unexpected=True)
                self._publish_diagnostics()
                return answer
            self._calls.count(service, "" if answer.success else answer.message)
            self._publish_diagnostics()
            return answer
        return callback

    def _in_force(self) -> str:
        lights = f"lights of {self._lights.date}" if self._lights is not None else "no lights"
        flat = (f"flat field of {self._flat.date}" if self._flat is not None
                else "no flat field")
        return f"in force: {lights}, {flat}"

    def _publish_diagnostics(self) -> None:
        calls = self._calls.snapshot()
        status = DiagnosticStatus(name=f"{self.get_name()}: calibration")
        if calls["last_unexpected"]:
            status.level = DiagnosticStatus.ERROR
        elif calls["last_refused"]:
            status.level = DiagnosticStatus.WARN
        else:
            status.level = DiagnosticStatus.OK
        status.message = (_one_line(calls["last_error"]) if status.level != DiagnosticStatus.OK
                          else "ok")
        status.values = [
            KeyValue(key="calls_ok", value=str(calls["ok"])),
            KeyValue(key="calls_refused", value=str(calls["refused"])),
            KeyValue(key="calls_failed_unexpectedly", value=str(calls["unexpected"])),
            KeyValue(key="last_error", value=_one_line(calls["last_error"])),
            KeyValue(key="lights_in_force",
                     value=self._lights.date if self._lights is not None else ""),
            KeyValue(key="flat_field_in_force",
                     value=self._flat.date if self._flat is not None else ""),
        ]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)

    # ------------------------------------------------------------------ saved calibration
    def _load_saved(self) -> None:
        """Load and publish the saved calibration, if any (errors are logged, not fatal:
        the operator can recalibrate, which replaces the files)."""
        if self._dir is None:
            return
        name = str(self.get_parameter("camera_name").value)
        log = self.get_logger()
        try:
            flat = load_flat_field(self._dir)
        except FingerpsCalibError as exc:
            log.error(f"saved flat field not loaded: {exc}")
            flat = None
        if flat is not None and (problems := flat_field_problems(
                flat.portions, flat.relative_intensities)):
            log.error(f"saved flat field in {self._dir} not loaded: {'; '.join(problems)}; "
                      "recalibrate")
            flat = None
        if flat is not None and flat.camera_name != name:
            log.warning(f"saved flat field in {self._dir} is for camera {flat.camera_name!r}, "
                        f"this node's camera_name is {name!r}: not loaded; recalibrate")
            flat = None
        if flat is not None:
            self._flat = flat
            self._pub_flat.publish(self._flat_message(flat))
            log.info(f"loaded the flat field of {flat.date} ({flat.portions.shape[0]} maps "
                     f"{flat.portions.shape[2]}x{flat.portions.shape[1]}) from "
                     f"{self._dir / FLAT_FIELD_FILE}; published")
        try:
            lights = load_lights(self._dir)
        except FingerpsCalibError as exc:
            log.error(f"saved light calibration not loaded: {exc}")
            lights = None
        if lights is not None and (problems := lights_problems(
                lights.lights.directions_optical, self._intensities(lights.lights.led_count),
                led_positions_optical_m=lights.lights.led_positions_optical_m)):
            log.error(f"saved light calibration in {self._dir} not loaded: "
                      f"{'; '.join(problems)}; recalibrate")
            lights = None
        if lights is not None and lights.camera_name != name:
            log.warning(f"saved light calibration in {self._dir} is for camera "
                        f"{lights.camera_name!r}, this node's camera_name is {name!r}: not "
                        "loaded; recalibrate")
            lights = None
        if lights is not None:
            self._lights = lights
            self._lights_msg = self._lights_message(lights)
            self._pub_lights.publish(self._lights_msg)
            log.info(f"loaded the light calibration of {lights.date} ({lights.lights.led_count} "
                     f"LEDs, {len(lights.lights.placements)} placement(s)) from "
                     f"{self._dir / LIGHTS_FILE}; published")

    # ------------------------------------------------------------------ images
    def _frames(self, given: list[TaggedFrame], *, with_dark: bool
                ) -> tuple[list[TaggedFrame], CameraInfo | None, np.ndarray | None]:
        """The request's frames, or a fresh burst from the driver (with a dark frame if
        asked); sorted by LED. Returns (frames, camera info, dark image or None)."""
        if given:
            lit = [f for f in given if f.led_index != TaggedFrame.LED_DARK]
            darks = [_pixels(f) for f in given if f.led_index == TaggedFrame.LED_DARK]
            return (sorted(lit, key=lambda f: f.led_index), self._camera_info,
                    darks[0] if darks else None)
        timeout = float(self.get_parameter("capture_timeout").value)
        if not self._capture.wait_for_service(timeout_sec=timeout):
            raise FingerpsCalibError(
                f"no images in the request and the driver's {self._capture.srv_name} service "
                "is not available: start driver_node or send the images in the request")
        done = threading.Event()
        future = self._capture.call_async(
            CaptureBurst.Request(response_only=True, with_dark_frame=with_dark))
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise FingerpsCalibError(
                f"the driver did not answer within {timeout} s; check driver_node")
        response = future.result()
        if response is None or not response.success:
            reason = response.message if response is not None else "no response"
            raise FingerpsCalibError(f"the driver's burst failed: {reason}")
        burst = response.burst
        dark = _pixels(burst.dark_frame) if burst.has_dark_frame else None
        return sorted(burst.frames, key=lambda f: f.led_index), burst.camera_info, dark

    @staticmethod
    def _stack(frames: list[TaggedFrame]) -> np.ndarray:
        indices = [f.led_index for f in frames]
        count = frames[0].led_count if frames else 0
        if not frames or indices != list(range(count)):
            raise FingerpsCalibError(
                f"expected one frame per LED 0..{max(count - 1, 0)}, got LEDs {indices}: "
                "capture a whole burst")
        images = [_pixels(f) for f in frames]
        shapes = {im.shape for im in images}
        if len(shapes) != 1:
            raise FingerpsCalibError(f"frames of different sizes {sorted(shapes)}; recapture")
        if images[0].ndim != 2:
            raise FingerpsCalibError(
                f"frames are {frames[0].image.encoding}; the calibration needs mono8, mono16 "
                "or 32FC1 images")
        return np.stack(images)

    @staticmethod
    def _check_min_size(images: np.ndarray) -> None:
        h, w = images.shape[1:]
        if min(h, w) < MIN_IMAGE_SIDE_PX:
            raise FingerpsCalibError(
                f"frames are {w}x{h} px; a calibration needs whole camera frames of at least "
                f"{MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX} (the flat field is fitted to 64 "
                "blocks across the short side, the sphere's silhouette needs pixels): send "
                "full frames, or no frames to capture a burst through the driver")

    def _camera(self, info: CameraInfo | None) -> _Camera | None:
        """The intrinsics to use: camera_info_file if set, else the driver's camera_info."""
        if self._file_camera is not None:
            c = self._file_camera
            return _Camera(np.array(c.camera_matrix), _distortion(c.distortion_model,
                                                                 c.distortion),
                           c.width, c.height, f"camera_info_file ({c.camera_name})")
        if info is None or info.k[0] <= 0:
            return None
        if not np.all(np.isfinite(info.k)) or not np.all(np.isfinite(info.d)):
            raise FingerpsCalibError(
                "the driver's camera_info has intrinsics that are not finite (K or D); fix "
                "the driver's camera_info_file or set calib_node's camera_info_file")
        return _Camera(np.reshape(np.asarray(info.k, dtype=np.float64), (3, 3)),
                       _distortion(info.distortion_model, np.asarray(info.d, dtype=float)),
                       int(info.width), int(info.height), "the driver's camera_info")

    def _image_size(self, info: CameraInfo | None) -> tuple[int, int, str] | None:
        """(width, height, source) of the camera's images, when known."""
        if self._file_camera is not None and self._file_camera.width > 0:
            c = self._file_camera
            return c.width, c.height, f"camera_info_file ({c.camera_name})"
        if info is not None and info.width > 0 and info.height > 0:
            return int(info.width), int(info.height), "the driver's camera_info"
        return None

    @staticmethod
    def _check_size(images: np.ndarray, camera: _Camera | None) -> None:
        if camera is None or camera.width <= 0:
            return
        h, w = images.shape[1:]
        if (w, h) != (camera.width, camera.height):
            raise FingerpsCalibError(
                f"the images are {w}x{h} but the intrinsics ({camera.source}) are for "
                f"{camera.width}x{camera.height}: use the camera the intrinsics belong to, or "
                "the intrinsics of this camera")

    def _full_scale(self, frames: list[TaggedFrame]) -> float | None:
        encoding = frames[0].image.encoding
        if encoding == "mono8":
            return 255.0
        if encoding == "mono16":
            return float(self.get_parameter("mono16_full_scale").value)
        return None

    # ------------------------------------------------------------------ lights
    def _on_lights(self, request: CalibrateLights.Request,
                   response: CalibrateLights.Response) -> CalibrateLights.Response:
        radius = request.sphere_radius or float(self.get_parameter("sphere_radius").value)
        images, result, camera = None, None, None
        try:
            try:
                check_radius(radius)
            except FingerpsCalibError:
                lo, hi = RADIUS_RANGE_M
                raise FingerpsCalibError(
                    f"sphere_radius {radius!r} m in the request: the radius of a calibration "
                    f"sphere must be finite and between {lo:g} and {hi:g} m "
                    f"({1e3 * lo:g}-{1e3 * hi:g} mm); give the sphere's radius in metres "
                    "(0.004 for a ball of 8 mm), or 0 for calib_node's sphere_radius "
                    f"({self.get_parameter('sphere_radius').value:g} m)") from None
            frames, info, _ = self._frames(list(request.frames), with_dark=False)
            images = self._stack(frames)
            camera = self._camera(info)
            if camera is None:
                raise FingerpsCalibError(
                    ("no camera intrinsics: start driver_node (its camera_info)"
                     if info is None else
                     "the driver's camera_info has no intrinsics (K = 0): set the driver's")
                    + " or calib_node's camera_info_file (make one with `ros2 run "
                    "fingerps_calib calibrate_camera` from checkerboard images)")
            self._check_min_size(images)
            self._check_size(images, camera)
            reference = np.asarray(self.get_parameter("reference_point").value, dtype=float)
            tolerance = float(self.get_parameter("sphere_distance_tolerance").value)
            distance = float(np.linalg.norm(reference))
            result = calibrate_lights(
                images, camera_matrix=camera.matrix, radius_m=radius,
                distortion=camera.distortion, saturation_level=self._full_scale(frames),
                require_whole_sphere=True,
                expected_distance_m=(distance * (1 - tolerance), distance * (1 + tolerance)))
            if not result.ok:
                raise _RefusedError("light calibration failed its checks: "
                               + "; ".join(result.problems), result.problems)
            placements = [Placement.from_result(result)]
            if request.add_placement and self._lights is not None:
                self._check_compatible(self._lights, images, camera)
                placements = [*self._lights.lights.placements, *placements]
            combined = combine_placements(placements, reference_point_optical_m=reference)
            if not combined.ok:
                raise _RefusedError(
                    f"the {len(placements)} sphere placements do not combine (this placement "
                    "is not added): " + "; ".join(combined.problems), combined.problems)
            frame_id = (info.header.frame_id if info is not None and info.header.frame_id
                        else frames[0].header.frame_id or DEFAULT_FRAME_ID)
            h, w = images.shape[1:]
            record = LightsRecord(
                camera_name=str(self.get_parameter("camera_name").value), frame_id=frame_id,
                stamp_ns=self.get_clock().now().nanoseconds, image_width=w, image_height=h,
                camera_matrix=camera.matrix, lights=combined)
            msg = self._lights_message(record)
            problems = tuple(lights_problems(
                combined.directions_optical, msg.relative_intensities,
                led_positions_optical_m=combined.led_positions_optical_m))
            if problems:
                raise _RefusedError("the light calibration is not usable (not put in force): "
                                    + "; ".join(problems), problems)
        except _RefusedError as exc:
            return self._refuse_lights(response, str(exc), exc.problems, images, result,
                                       camera)
        except FingerpsCalibError as exc:
            return self._refuse_lights(response, str(exc), (str(exc),), images, result,
                                       camera)
        self._lights, self._lights_msg = record, msg
        self._pub_lights.publish(msg)
        saved = self._save_lights(record, images, result, camera)
        response.success, response.calibration = True, msg
        response.message = _lights_summary(record) + saved
        self.get_logger().info(response.message)
        return response

    def _check_compatible(self, in_force: LightsRecord, images: np.ndarray,
                          camera: _Camera) -> None:
        restart = "calibrate with add_placement=false to start a new set of placements"
        n_led, h, w = images.shape
        if in_force.lights.led_count != n_led:
            raise FingerpsCalibError(
                f"add_placement: the calibration in force has {in_force.lights.led_count} "
                f"LEDs, these images {n_led}; {restart}")
        if (in_force.image_width, in_force.image_height) != (w, h) or not np.allclose(
                in_force.camera_matrix, camera.matrix, rtol=1e-9, atol=1e-9):
            raise FingerpsCalibError(
                "add_placement: the camera (image size or intrinsics) differs from the "
                f"calibration in force's; {restart}")

    def _refuse_lights(self, response: CalibrateLights.Response, message: str,
                       problems: tuple[str, ...], images: np.ndarray | None,
                       result: LightCalibrationResult | None,
                       camera: _Camera | None) -> CalibrateLights.Response:
        response.success, response.message = False, message
        if self._lights is not None:
            response.message += (f" [the calibration of {self._lights.date} stays in force]")
        if images is not None and result is not None and camera is not None \
                and self._dir is not None:
            try:
                picture = _picture(
                    images, result, camera, result.directions_optical, (),
                    title="light calibration REFUSED",
                    lines=[f"camera {self.get_parameter('camera_name').value}, "
                           f"{iso_date(self.get_clock().now().nanoseconds)}"],
                    problems=problems)
                path = write_png(self._dir / "lights_rejected.png", picture)
                response.message += f" [picture: {path}]"
            except FingerpsCalibError as exc:
                self.get_logger().warning(f"no picture of the refused calibration: {exc}")
        self.get_logger().error(f"light calibration refused: {response.message}")
        return response

    def _save_lights(self, record: LightsRecord, images: np.ndarray,
                     result: LightCalibrationResult, camera: _Camera) -> str:
        if self._dir is None:
            return "; not saved (calibration_dir is empty)"
        try:
            path = save_lights(self._dir, record)
        except FingerpsCalibError as exc:
            self.get_logger().error(f"light calibration in force but NOT SAVED: {exc}")
            return f"; NOT SAVED: {exc}"
        text = f"; saved to {path}"
        try:
            placements = record.lights.placements
            picture = _picture(
                images, result, camera, record.lights.directions_optical,
                [pl.directions_optical for pl in placements] if len(placements) > 1 else [],
                title="light calibration in force", lines=_lights_lines(record))
            text += f"; picture {write_png(self._dir / LIGHTS_PICTURE, picture)}"
        except FingerpsCalibError as exc:
            self.get_logger().warning(f"no picture of the light calibration: {exc}")
        return text

    def _lights_message(self, record: LightsRecord) -> LightCalibration:
        lights = record.lights
        header = Header(frame_id=record.frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(int(record.stamp_ns), 1_000_000_000)
        centre = lights.sphere_center_optical_m
        return LightCalibration(
            header=header, camera_name=record.camera_name,
            directions=[Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2]))
                        for d in lights.directions_optical],
            relative_intensities=self._intensities(lights.led_count),
            residuals=[float(r) for r in lights.residuals_px],
            sphere_radius=float(lights.placements[-1].radius_m),
            sphere_center=Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2])),
            edge_fit_residual=float(lights.edge_rms_px),
            placements=len(lights.placements),
            led_positions=[Point(x=float(q[0]), y=float(q[1]), z=float(q[2]))
                           for q in lights.led_positions_optical_m])

    def _intensities(self, count: int) -> list[float]:
        if self._flat is not None and len(self._flat.relative_intensities) == count:
            return [float(x) for x in self._flat.relative_intensities]
        return [1.0] * count

    # ------------------------------------------------------------------ flat field
    def _on_flat(self, request: CalibrateFlatField.Request,
                 response: CalibrateFlatField.Response) -> CalibrateFlatField.Response:
        degree = int(self.get_parameter("flat_field_degree").value)
        try:
            frames, info, dark = self._frames(list(request.frames), with_dark=True)
            images = self._stack(frames)
            self._check_min_size(images)
            size = self._image_size(info)
            if size is not None and (images.shape[2], images.shape[1]) != size[:2]:
                raise FingerpsCalibError(
                    f"the white-target frames are {images.shape[2]}x{images.shape[1]}, the "
                    f"camera's images ({size[2]}) {size[0]}x{size[1]}: send whole frames of "
                    "this camera, or no frames to capture a burst through the driver")
            if dark is not None and dark.shape != images.shape[1:]:
                raise FingerpsCalibError(
                    f"the dark frame is {dark.shape[1]}x{dark.shape[0]}, the images "
                    f"{images.shape[2]}x{images.shape[1]}; recapture")
            result = flat_field_maps(images, dark=dark, saturation_level=self._full_scale(frames),
                                     polynomial_degree=degree)
            problems = flat_field_problems(
                result.portions, result.relative_intensities,
                image_size=size[:2] if size is not None else None)
            if problems:
                raise FingerpsCalibError("the flat field is not usable (not put in force): "
                                         + "; ".join(problems))
        except FingerpsCalibError as exc:
            response.success, response.message = False, str(exc)
            if self._flat is not None:
                response.message += f" [the flat field of {self._flat.date} stays in force]"
            self.get_logger().error(f"flat-field calibration refused: {response.message}")
            return response
        record = FlatFieldRecord(
            camera_name=str(self.get_parameter("camera_name").value),
            frame_id=frames[0].header.frame_id or DEFAULT_FRAME_ID,
            stamp_ns=self.get_clock().now().nanoseconds, portions=result.portions,
            relative_intensities=result.relative_intensities,
            fit_residuals=result.fit_residuals, polynomial_degree=degree)
        msg = self._flat_message(record)
        self._flat = record
        self._pub_flat.publish(msg)
        if self._lights is not None and self._lights.lights.led_count == len(frames):
            self._lights_msg = self._lights_message(self._lights)
            self._pub_lights.publish(self._lights_msg)
        response.success, response.flat_field = True, msg
        response.message = (
            f"{len(frames)} flat-field maps; relative intensities "
            + ", ".join(f"{x:.2f}" for x in result.relative_intensities)
            + "; fit residual max " + f"{100 * np.max(result.fit_residuals):.2f}%"
            + self._save_flat(record))
        self.get_logger().info(response.message)
        return response

    def _save_flat(self, record: FlatFieldRecord) -> str:
        if self._dir is None:
            return "; not saved (calibration_dir is empty)"
        try:
            path = save_flat_field(self._dir, record)
        except FingerpsCalibError as exc:
            self.get_logger().error(f"flat field in force but NOT SAVED: {exc}")
            return f"; NOT SAVED: {exc}"
        text = f"; saved to {path}"
        try:
            picture = flat_field_picture(
                record.portions, relative_intensities=record.relative_intensities,
                fit_residuals=record.fit_residuals, title="flat field in force",
                lines=[f"camera {record.camera_name}, {record.date}; polynomial degree "
                       f"{record.polynomial_degree}"])
            text += f"; picture {write_png(self._dir / FLAT_FIELD_PICTURE, picture)}"
        except FingerpsCalibError as exc:
            self.get_logger().warning(f"no picture of the flat field: {exc}")
        return text

    @staticmethod
    def _flat_message(record: FlatFieldRecord) -> FlatField:
        header = Header(frame_id=record.frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(int(record.stamp_ns), 1_000_000_000)
        return FlatField(
            header=header, camera_name=record.camera_name,
            maps=[array_to_image(m, encoding="32FC1", header=header) for m in record.portions],
            relative_intensities=[float(x) for x in record.relative_intensities])


class _RefusedError(FingerpsCalibError):
    """A calibration that failed its checks, with the list of problems."""

    def __init__(self, message: str, problems: tuple[str, ...]) -> None:
        super().__init__(message)
        self.problems = problems


def _picture(images: np.ndarray, result: LightCalibrationResult, camera: _Camera,
             directions: np.ndarray, placement_directions: list[np.ndarray], *, title: str,
             lines: list[str], problems: tuple[str, ...] = ()) -> np.ndarray:
    """The operator's picture of a light calibration (in the raw image's pixels)."""
    return lights_picture(
        images,
        highlights_uv=distort_points(result.highlights_uv, camera.matrix, camera.distortion),
        directions_optical=directions, edge_points_uv=result.edge_points_uv,
        outline_uv=sphere_outline(result.sphere_center_optical_m, result.radius_m,
                                  camera.matrix, camera.distortion),
        placement_directions=placement_directions, title=title, lines=lines,
        problems=problems)


def _pixels(frame: TaggedFrame) -> np.ndarray:
    try:
        return image_to_array(frame.image)
    except FingerpsError as exc:
        raise FingerpsCalibError(f"LED {frame.led_index}: {exc}") from exc


def _distortion(model: str, coefficients: np.ndarray) -> np.ndarray | None:
    coefficients = np.asarray(coefficients, dtype=np.float64).ravel()
    if not np.any(coefficients):
        return None
    if model in ("plumb_bob", "rational_polynomial"):
        return coefficients
    raise FingerpsCalibError(
        f"distortion model {model!r} is not supported by the light calibration; give "
        "rectified images with plumb_bob intrinsics")


def _check_reference_point(value: object) -> str | None:
    try:
        point = [float(x) for x in value]  # a ROS double array is an array.array
    except (TypeError, ValueError):
        point = []
    if len(point) != 3 or not all(math.isfinite(x) for x in point) or not point[2] > 0:
        return ("must be three finite numbers (x, y, z) in metres with z > 0 (in front of "
                "the camera), e.g. [0.0, 0.0025, 0.09]")
    return None


def _check_camera_name(value: object) -> str | None:
    if not isinstance(value, str) or not value.strip():
        return ("must not be empty: it names the camera in every calibration (and a saved "
                "calibration is loaded only for the same name), e.g. fingerps_sim")
    return None


def _check_sphere_radius(value: object) -> str | None:
    try:
        check_radius(value)
    except FingerpsCalibError:
        lo, hi = RADIUS_RANGE_M
        return (f"must be a finite radius in metres between {lo:g} and {hi:g} "
                f"({1e3 * lo:g}-{1e3 * hi:g} mm), e.g. 0.004 for a ball of 8 mm")
    return None


def _check_finite(value: object) -> str | None:
    try:
        finite = math.isfinite(float(value))
    except (TypeError, ValueError):
        finite = False
    return None if finite else "must be a finite number"


def _one_line(text: str) -> str:
    """``text`` on one line (exception texts can hold newlines), at most 500 characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= 500 else line[:497] + "..."


class _Calls:
    """Counts of the service calls answered (thread-safe), for /diagnostics."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._ok = self._refused = self._unexpected = 0
        self._last_error = ""
        self._last_refused = self._last_unexpected = False

    def count(self, service: str, error: str, *, unexpected: bool = False) -> None:
        """Count one answer; ``error`` empty for success."""
        with self._lock:
            if unexpected:
                self._unexpected += 1
            elif error:
                self._refused += 1
            else:
                self._ok += 1
            if error:
                self._last_error = f"{service}: {error}"
            self._last_refused = bool(error)
            self._last_unexpected = unexpected

    def snapshot(self) -> dict:
        with self._lock:
            return {"ok": self._ok, "refused": self._refused, "unexpected": self._unexpected,
                    "last_error": self._last_error, "last_refused": self._last_refused,
                    "last_unexpected": self._last_unexpected}


def _lights_summary(record: LightsRecord) -> str:
    lights = record.lights
    centre = 1e3 * lights.sphere_center_optical_m
    text = (f"{lights.led_count} LEDs calibrated from {len(lights.placements)} sphere "
            f"placement(s); sphere centre ({centre[0]:.2f}, {centre[1]:.2f}, {centre[2]:.2f}) "
            f"mm, edge rms {lights.edge_rms_px:.2f} px, highlight residual max "
            f"{np.nanmax(lights.residuals_px):.2f} px")
    tri = lights.triangulation
    if tri is not None:
        ref = 1e3 * tri.reference_point_optical_m
        text += (f"; LED positions triangulated (residual max "
                 f"{1e3 * np.nanmax(tri.position_residuals_m):.2f} mm, rays "
                 f"{np.nanmin(tri.ray_angles_deg):.1f}-{np.nanmax(tri.ray_angles_deg):.1f} deg "
                 f"apart), directions from ({ref[0]:.1f}, {ref[1]:.1f}, {ref[2]:.1f}) mm")
    return text


def _lights_lines(record: LightsRecord) -> list[str]:
    """Text under the light calibration's picture."""
    lights = record.lights
    lines = [f"camera {record.camera_name}, {record.date}", _lights_summary(record)]
    tri = lights.triangulation
    for k, d in enumerate(lights.directions_optical):
        polar = np.degrees(np.arccos(np.clip(-d[2], -1, 1)))
        azimuth = np.degrees(np.arctan2(-d[1], d[0]))
        line = (f"LED {k}: {polar:.1f} deg from the view axis, azimuth {azimuth:.0f} deg, "
                f"highlight residual {lights.residuals_px[k]:.2f} px")
        if tri is not None:
            q = 1e3 * tri.led_positions_optical_m[k]
            line += (f", at ({q[0]:.1f}, {q[1]:.1f}, {q[2]:.1f}) mm +- "
                     f"{1e3 * tri.position_residuals_m[k]:.2f} mm")
        lines.append(line)
    return lines


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_calib calib_node``."""
    return run_node(CalibNode, args=args, name="calib_node", executor=MultiThreadedExecutor,
                    expected_errors=(FingerpsCalibError,))


if __name__ == "__main__":
    raise SystemExit(main())
