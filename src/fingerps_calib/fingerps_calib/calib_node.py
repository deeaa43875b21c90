"""calib_node: light directions from a shiny sphere and flat-field maps from a white target.

Thin ROS adapter around ``fingerps_calib.sphere_calibration.calibrate_lights`` and
``fingerps_calib.flat_field_calibration.flat_field_maps``. The services take the images in
the request, or, when the request has none, ask the driver for a burst. A calibration that
fails its checks is not published; the last good one stays in force. Both calibrations are
published reliable and transient-local, so nodes that start later still receive them.
"""

from __future__ import annotations

import threading

import numpy as np
from geometry_msgs.msg import Point, Vector3
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_calib.sphere_calibration import calibrate_lights
from fingerps_msgs.msg import FlatField, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights, CaptureBurst
from fingerps_recon import qos, topics
from fingerps_recon.image_conversion import array_to_image, image_to_array
from fingerps_recon.node_runner import run_node
from fingerps_recon.parameters import ParameterChecks, descriptor


class CalibNode(Node):
    """Serves the calibration services and publishes the calibration in force."""

    def __init__(self) -> None:
        super().__init__("calib", namespace=topics.NAMESPACE)
        self._checks = ParameterChecks(self)
        p = self.declare_parameter
        p("sphere_radius", 0.004, descriptor(
            "Radius of the calibration sphere, metres (used when a request gives 0)",
            min_value=1e-4, max_value=0.1))
        p("capture_timeout", 5.0, descriptor(
            "Seconds to wait for the driver's burst when a request carries no images",
            min_value=0.1, max_value=60.0))
        p("flat_field_degree", 4, descriptor(
            "Degree of the smooth 2D polynomial fitted to each white-target image (so paper "
            "texture and noise do not enter the flat-field maps)", min_value=1, max_value=10,
            integer=True))
        p("camera_name", "fingerps_sim", descriptor("Camera name written into calibrations"))

        self._checks.refuse_unknown_overrides(self)

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
        self.create_service(CalibrateLights, topics.CALIBRATE_LIGHTS, self._on_lights,
                            callback_group=self._service_group)
        self.create_service(CalibrateFlatField, topics.CALIBRATE_FLAT_FIELD, self._on_flat,
                            callback_group=self._service_group)
        self._lights: LightCalibration | None = None
        self._flat: FlatField | None = None
        self.get_logger().info("calib ready")

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self._camera_info = msg

    # ------------------------------------------------------------------ images
    def _frames(self, given: list[TaggedFrame], *, with_dark: bool
                ) -> tuple[list[TaggedFrame], CameraInfo | None, np.ndarray | None]:
        """The request's frames, or a fresh burst from the driver (with a dark frame if
        asked); sorted by LED. Returns (frames, camera info, dark image or None)."""
        if given:
            lit = [f for f in given if f.led_index != TaggedFrame.LED_DARK]
            darks = [image_to_array(f.image) for f in given
                     if f.led_index == TaggedFrame.LED_DARK]
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
        dark = image_to_array(burst.dark_frame.image) if burst.has_dark_frame else None
        return sorted(burst.frames, key=lambda f: f.led_index), burst.camera_info, dark

    @staticmethod
    def _stack(frames: list[TaggedFrame]) -> np.ndarray:
        indices = [f.led_index for f in frames]
        count = frames[0].led_count if frames else 0
        if not frames or indices != list(range(count)):
            raise FingerpsCalibError(
                f"expected one frame per LED 0..{max(count - 1, 0)}, got LEDs {indices}: "
                "capture a whole burst")
        images = [image_to_array(f.image) for f in frames]
        shapes = {im.shape for im in images}
        if len(shapes) != 1:
            raise FingerpsCalibError(f"frames of different sizes {sorted(shapes)}; recapture")
        return np.stack(images)

    # ------------------------------------------------------------------ services
    def _on_lights(self, request: CalibrateLights.Request,
                   response: CalibrateLights.Response) -> CalibrateLights.Response:
        radius = request.sphere_radius or float(self.get_parameter("sphere_radius").value)
        try:
            if radius <= 0:
                raise FingerpsCalibError(f"sphere_radius must be > 0 m, got {radius}")
            frames, info, _ = self._frames(list(request.frames), with_dark=False)
            images = self._stack(frames)
            if info is None or info.k[0] <= 0:
                raise FingerpsCalibError(
                    "no camera intrinsics: the light calibration needs the camera_info of the "
                    "driver; start driver_node first")
            result = calibrate_lights(images, camera_matrix=np.reshape(info.k, (3, 3)),
                                      radius_m=radius)
        except FingerpsCalibError as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().error(f"light calibration refused: {exc}")
            return response
        if not result.ok:
            response.success = False
            response.message = "light calibration failed its checks: " + "; ".join(
                result.problems)
            self.get_logger().error(response.message)
            return response
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id=info.header.frame_id)
        msg = LightCalibration(
            header=header, camera_name=str(self.get_parameter("camera_name").value),
            directions=[Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2]))
                        for d in result.directions_optical],
            relative_intensities=self._intensities(len(frames)),
            residuals=[float(r) for r in result.residuals_px],
            sphere_radius=float(radius),
            sphere_center=Point(x=float(result.sphere_center_optical_m[0]),
                                y=float(result.sphere_center_optical_m[1]),
                                z=float(result.sphere_center_optical_m[2])),
            edge_fit_residual=float(result.edge_rms_px))
        self._lights = msg
        self._pub_lights.publish(msg)
        response.success, response.calibration = True, msg
        response.message = (f"{len(frames)} LEDs calibrated; sphere edge rms "
                            f"{result.edge_rms_px:.2f} px, highlight residual max "
                            f"{np.max(result.residuals_px):.2f} px")
        self.get_logger().info(response.message)
        return response

    def _intensities(self, count: int) -> list[float]:
        if self._flat is not None and len(self._flat.relative_intensities) == count:
            return list(self._flat.relative_intensities)
        return [1.0] * count

    def _on_flat(self, request: CalibrateFlatField.Request,
                 response: CalibrateFlatField.Response) -> CalibrateFlatField.Response:
        try:
            frames, _, dark = self._frames(list(request.frames), with_dark=True)
            images = self._stack(frames)
            full = 255.0 if frames[0].image.encoding == "mono8" else 4095.0
            result = flat_field_maps(
                images, dark=dark, saturation_level=full,
                polynomial_degree=int(self.get_parameter("flat_field_degree").value))
        except FingerpsCalibError as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().error(f"flat-field calibration refused: {exc}")
            return response
        header = Header(stamp=self.get_clock().now().to_msg(),
                        frame_id=frames[0].header.frame_id)
        msg = FlatField(
            header=header, camera_name=str(self.get_parameter("camera_name").value),
            maps=[array_to_image(m, encoding="32FC1", header=header) for m in result.portions],
            relative_intensities=[float(x) for x in result.relative_intensities])
        self._flat = msg
        self._pub_flat.publish(msg)
        if self._lights is not None and len(self._lights.directions) == len(frames):
            self._lights.relative_intensities = list(msg.relative_intensities)
            self._pub_lights.publish(self._lights)
        response.success, response.flat_field = True, msg
        response.message = (f"{len(frames)} flat-field maps; relative intensities "
                            + ", ".join(f"{x:.2f}" for x in result.relative_intensities))
        self.get_logger().info(response.message)
        return response


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_calib calib_node``."""
    return run_node(CalibNode, args=args, name="calib_node", executor=MultiThreadedExecutor,
                    expected_errors=(FingerpsCalibError,))


if __name__ == "__main__":
    raise SystemExit(main())
