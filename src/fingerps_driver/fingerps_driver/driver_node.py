"""driver_node: switches the LEDs over serial, captures and tags bursts, publishes them.

Thin ROS adapter: the parameters (``driver_parameters``), the publishers and services with
their QoS, the messages (``burst_conversion``, ``driver_diagnostics``); the hardware and the
bursts are ``driver_core.DriverCore``: the board's connection (``board.board_connection``),
the camera (``cameras.camera_setup``), the sequencing (``capture.burst.capture_burst``).

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

import time
from collections.abc import Callable
from functools import partial

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from sensor_msgs.srv import SetCameraInfo
from std_msgs.msg import Header

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_conversion import (
    camera_info_to_intrinsics,
    intrinsics_to_camera_info,
)
from fingerps_driver.burst_conversion import burst_message, stamped_camera_info, tagged_frame
from fingerps_driver.cameras.camera_info_manager import CameraCalibration
from fingerps_driver.capture.burst import BurstResult
from fingerps_driver.driver_core import DriverCore
from fingerps_driver.driver_diagnostics import driver_statuses
from fingerps_driver.driver_parameters import (
    FINGER_POSE,
    board_settings,
    burst_plan,
    camera_settings,
    driver_parameters,
    finger_config,
)
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import Scene
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import qos, topics
from fingerps_ros.compressed_topics import CompressedTopics
from fingerps_ros.diagnostics import PERIOD_S, DiagnosticsPublisher
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import declare_parameters


class DriverNode(Node):
    """Captures bursts on demand (service) or continuously (``rate`` > 0)."""

    def __init__(self) -> None:
        super().__init__("driver", namespace=topics.NAMESPACE)
        self._checks = declare_parameters(self, driver_parameters(self._param))
        # image_raw/compressed as image_transport publishes it; off by default (7 PNGs a
        # burst); encoded only while subscribed, after the burst is out
        self._image_compressed = CompressedTopics(
            self, topics.IMAGE_RAW, qos.SENSOR_QOS, self._checks, enabled_by_default=False)
        self._checks.refuse_unknown_overrides(self)

        self._diagnostics = DiagnosticsPublisher(self, self._statuses)
        self._core = DriverCore(board_settings(self._param), camera_settings(self._param),
                                log=self.get_logger(), start_timer=self._one_shot,
                                on_board_change=self._diagnostics.publish)
        self._core.open(node_name=self.get_fully_qualified_name(),
                        image_topic=self.resolve_topic_name(topics.IMAGE_RAW))
        assert self._core.calibration is not None and self._core.camera is not None
        self._camera_info = self._info_of(self._core.calibration.current)

        self._pub_frames = self.create_publisher(TaggedFrame, topics.FRAMES, qos.SENSOR_QOS)
        self._pub_image = self.create_publisher(Image, topics.IMAGE_RAW, qos.SENSOR_QOS)
        self._pub_info = self.create_publisher(CameraInfo, topics.CAMERA_INFO, qos.SENSOR_QOS)
        self._pub_burst = self.create_publisher(Burst, topics.BURST, qos.BURST_QOS)
        self.create_service(CaptureBurst, topics.CAPTURE_BURST, self._on_capture)
        # camera_info_manager's service name, where camera_calibration's calibrator commits
        self.create_service(SetCameraInfo, "~/set_camera_info", self._on_set_camera_info)
        self.create_timer(PERIOD_S, self._on_diagnostics_timer)
        self._rate_timer = None
        self._apply_rate(self._param("rate"))
        self.add_post_set_parameters_callback(self._after_set)
        self._core.start()
        core, camera = self._core, self._core.camera
        self.get_logger().info(
            f"driver ready: board on {core.port} ({core.state.value}), "
            f"{self._param('led_count')} LEDs, order {list(burst_plan(self._param).led_order)}"
            f", camera {self._param('camera')} {camera.width}x{camera.height} "
            f"{camera.encoding}")

    # ------------------------------------------------------------------ parameters
    def _param(self, name: str) -> object:
        return self.get_parameter(name).value

    def _after_set(self, parameters: list) -> None:
        core = self._core
        for param in parameters:
            if param.name == "rate":
                self._apply_rate(param.value)
            elif param.name in ("sim.finger_motion_px", "sim.finger_motion_bursts"):
                core.set_sim_motion(self._param("sim.finger_motion_px"),
                                    int(self._param("sim.finger_motion_bursts")))
            elif param.name == "sim.sphere_center":
                core.move_sphere(param.value)
            elif param.name == "sim.scene":
                core.show(Scene(param.value))
        if any(p.name in FINGER_POSE for p in parameters):
            core.pose_finger(finger_config(self._param))

    def _apply_rate(self, rate: float) -> None:
        self._core.set_rate(rate)
        if self._rate_timer is not None:
            self.destroy_timer(self._rate_timer)
            self._rate_timer = None
        if rate > 0:
            self._rate_timer = self.create_timer(1.0 / rate, self._on_rate_timer)

    def _one_shot(self, delay_s: float, callback: Callable[[], None]) -> None:
        """Call ``callback`` once, ``delay_s`` from now (the board's reconnect attempts)."""
        timer = None

        def fire() -> None:
            self.destroy_timer(timer)
            callback()
        timer = self.create_timer(delay_s, fire)

    # ------------------------------------------------------------------ capture
    def _on_rate_timer(self) -> None:
        result = self._core.capture_continuous(burst_plan(self._param),
                                               with_dark=bool(self._param("with_dark_frame")))
        if result is not None and result.ok:
            self._publish(result, publish=True)

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
        result = self._core.capture(burst_plan(self._param), with_dark=with_dark,
                                    repeat_first=repeat_first)
        return result, (self._publish(result, publish=publish) if result.ok else None)

    def _publish(self, result: BurstResult, *, publish: bool) -> Burst:
        """Build the messages (and publish them); the time it takes is ``publish_ms``."""
        start = time.perf_counter()
        assert self._core.camera is not None
        tag = partial(tagged_frame, burst_id=result.burst_id,
                      led_count=int(self._param("led_count")),
                      encoding=self._core.camera.encoding, frame_id=str(self._param("frame_id")))
        tagged = [tag(f) for f in result.frames]
        if publish:
            for msg in tagged:  # in capture order, as they were taken
                self._pub_frames.publish(msg)
                self._pub_image.publish(msg.image)
        info = stamped_camera_info(self._camera_info, tagged[-1].header)
        burst = burst_message(result, tagged, info, tag)
        if publish:
            self._pub_info.publish(info)
            self._pub_burst.publish(burst)
            self._core.published((time.perf_counter() - start) * 1e3)
            for msg, frame in zip(tagged, result.frames, strict=True):
                self._image_compressed.publish(frame.image, msg.image.encoding, msg.header)
        return burst

    # ------------------------------------------------------------------ calibration
    def _info_of(self, calibration: CameraCalibration) -> CameraInfo:
        manager = self._core.calibration
        assert manager is not None
        return intrinsics_to_camera_info(calibration.intrinsics, width=manager.width,
                                         height=manager.height)

    def _on_set_camera_info(self, request: SetCameraInfo.Request,
                            response: SetCameraInfo.Response) -> SetCameraInfo.Response:
        """sensor_msgs/SetCameraInfo: validate, store to the URL's file, publish at once."""
        manager = self._core.calibration
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
        self._camera_info = self._info_of(calibration)
        self._pub_info.publish(stamped_camera_info(
            self._camera_info, Header(stamp=self.get_clock().now().to_msg(),
                                      frame_id=str(self._param("frame_id")))))
        response.success = True
        response.status_message = f"stored in {calibration.source}"
        self.get_logger().info(f"set_camera_info: calibration in force, {response.status_message}")
        return response

    # ------------------------------------------------------------------ diagnostics
    def _on_diagnostics_timer(self) -> None:
        if not self._core.check_port():  # a loss publishes them itself
            self._diagnostics.publish()

    def _statuses(self) -> list[DiagnosticStatus]:
        return driver_statuses(self.get_name(), self._core, self._image_compressed.failures)

    def destroy_node(self) -> None:
        """Switch the LEDs off and close the board and camera (idempotent)."""
        self._core.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_driver driver_node``."""
    return run_node(DriverNode, args=args, name="driver_node",
                    expected_errors=(FingerpsDriverError,))


if __name__ == "__main__":
    raise SystemExit(main())
