"""calib_node: light directions from a shiny sphere and flat-field maps from a white target.

Thin ROS adapter around ``fingerps_calib.calibration_keeper.CalibrationKeeper`` (the
calibration in force: ``lights.sphere_calibration.calibrate_lights``,
``lights.led_triangulation.combine_placements``, ``flat_field_calibration.flat_field_maps``,
their checks, saving and loading); ``calibration_messages`` converts the messages,
``calib_parameters`` declares the parameters, ``calib_diagnostics`` makes the status. The
services take the images in the request, or, when the request has none, ask the driver for
a burst. Camera intrinsics come from ``camera_info_file`` when it is set, else from the
driver's camera_info (``calibration_camera``).

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

from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo

from fingerps_calib.calib_diagnostics import ServiceCalls, calibration_status, one_line
from fingerps_calib.calib_parameters import calibration_settings, declare_calib_parameters
from fingerps_calib.calibration_keeper import CalibrationKeeper, Shots, open_calibration_dir
from fingerps_calib.calibration_messages import (
    burst_shots,
    flat_field_message,
    lights_message,
    request_shots,
)
from fingerps_calib.calibration_store import FlatFieldRecord, LightsRecord
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import load_camera_info
from fingerps_msgs.msg import Burst, FlatField, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights, CaptureBurst
from fingerps_ros import qos, topics
from fingerps_ros.diagnostics import PERIOD_S, DiagnosticsPublisher
from fingerps_ros.node_runner import StartupError, run_node
from fingerps_ros.service_call import call_service


class CalibNode(Node):
    """Serves the calibration services and publishes the calibration in force."""

    def __init__(self) -> None:
        super().__init__("calib", namespace=topics.NAMESPACE)
        self._checks = declare_calib_parameters(self)
        info_file = str(self.get_parameter("camera_info_file").value)
        file_camera = load_camera_info(info_file) if info_file else None  # error: exit 2
        try:
            directory = open_calibration_dir(str(self.get_parameter("calibration_dir").value))
        except FingerpsCalibError as exc:
            raise StartupError(str(exc)) from None

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
        self._calls = ServiceCalls()
        # the last calibration published: a service's answer is the message the keeper has
        # just published (it publishes what it puts in force before it answers)
        self._sent_lights: LightCalibration | None = None
        self._sent_flat: FlatField | None = None
        self._diagnostics = DiagnosticsPublisher(self, self._statuses)
        self._keeper = CalibrationKeeper(
            directory, file_camera=file_camera, log=self.get_logger(),
            now_ns=lambda: self.get_clock().now().nanoseconds,
            publish_lights=self._publish_lights, publish_flat=self._publish_flat)
        self._keeper.load_saved(str(self.get_parameter("camera_name").value))
        self.create_service(CalibrateLights, topics.CALIBRATE_LIGHTS,
                            self._answering("calibrate_lights", self._on_lights),
                            callback_group=self._service_group)
        self.create_service(CalibrateFlatField, topics.CALIBRATE_FLAT_FIELD,
                            self._answering("calibrate_flat_field", self._on_flat),
                            callback_group=self._service_group)
        self.create_timer(PERIOD_S, self._diagnostics.publish)
        source = f"camera_info_file {info_file}" if info_file else "the driver's camera_info"
        where = str(directory) if directory is not None else "nowhere (calibration_dir empty)"
        self.get_logger().info(f"calib ready: intrinsics from {source}; calibrations saved "
                               f"to {where}")

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self._camera_info = msg

    def _publish_lights(self, record: LightsRecord, intensities: list[float]) -> None:
        self._sent_lights = lights_message(record, intensities)
        self._pub_lights.publish(self._sent_lights)

    def _publish_flat(self, record: FlatFieldRecord) -> None:
        self._sent_flat = flat_field_message(record)
        self._pub_flat.publish(self._sent_flat)

    # ------------------------------------------------------------------ answers, diagnostics
    def _answering(self, service: str, handler: Callable) -> Callable:
        """``handler`` as a service callback that always answers: an unexpected exception is
        logged in one line, counted, and answered with success false and its reason."""
        def callback(request, response):
            try:
                answer = handler(request, response)
            except Exception as exc:  # every call gets an answer
                text = one_line(f"{type(exc).__name__}: {exc}")
                answer = type(response)()
                answer.success = False
                answer.message = (
                    f"{service} failed unexpectedly ({text}); {self._keeper.in_force()}; "
                    "check the request's frames and calib_node's parameters, and report "
                    "this error with calib_node's log if they are right")
                self.get_logger().error(f"{service}: unexpected error, answered with "
                                        f"success false: {text}")
                self._calls.count(service, answer.message, unexpected=True)
                self._diagnostics.publish()
                return answer
            self._calls.count(service, "" if answer.success else answer.message)
            self._diagnostics.publish()
            return answer
        return callback

    def _statuses(self) -> list[DiagnosticStatus]:
        lights, flat = self._keeper.lights, self._keeper.flat
        return [calibration_status(self.get_name(), self._calls.snapshot(),
                                   lights_date=lights.date if lights is not None else "",
                                   flat_field_date=flat.date if flat is not None else "")]

    # ------------------------------------------------------------------ images
    def _shots(self, given: list[TaggedFrame], *, with_dark: bool) -> Shots:
        """The request's frames, or a fresh burst from the driver (with a dark frame if
        asked)."""
        if given:
            return request_shots(given, self._camera_info)
        return burst_shots(self._capture_burst(with_dark=with_dark))

    def _capture_burst(self, *, with_dark: bool) -> Burst:
        """A burst captured by the driver for calibration (not published)."""
        timeout = float(self.get_parameter("capture_timeout").value)
        if not self._capture.wait_for_service(timeout_sec=timeout):
            raise FingerpsCalibError(
                f"no images in the request and the driver's {self._capture.srv_name} service "
                "is not available: start driver_node or send the images in the request")
        response = call_service(
            self._capture, CaptureBurst.Request(response_only=True, with_dark_frame=with_dark),
            timeout)
        if response is None:
            raise FingerpsCalibError(
                f"the driver did not answer within {timeout} s; check driver_node")
        if not response.success:
            raise FingerpsCalibError(f"the driver's burst failed: {response.message}")
        return response.burst

    # ------------------------------------------------------------------ services
    def _on_lights(self, request: CalibrateLights.Request,
                   response: CalibrateLights.Response) -> CalibrateLights.Response:
        answer = self._keeper.calibrate_lights(
            lambda: self._shots(list(request.frames), with_dark=False),
            sphere_radius_m=request.sphere_radius, add_placement=request.add_placement,
            settings=calibration_settings(self))
        response.success, response.message = answer.success, answer.message
        if answer.lights is not None and self._sent_lights is not None:  # just published
            response.calibration = self._sent_lights
        return response

    def _on_flat(self, request: CalibrateFlatField.Request,
                 response: CalibrateFlatField.Response) -> CalibrateFlatField.Response:
        answer = self._keeper.calibrate_flat_field(
            lambda: self._shots(list(request.frames), with_dark=True),
            settings=calibration_settings(self))
        response.success, response.message = answer.success, answer.message
        if answer.flat is not None and self._sent_flat is not None:  # just published
            response.flat_field = self._sent_flat
        return response


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_calib calib_node``."""
    return run_node(CalibNode, args=args, name="calib_node", executor=MultiThreadedExecutor,
                    expected_errors=(FingerpsCalibError,))


if __name__ == "__main__":
    raise SystemExit(main())
