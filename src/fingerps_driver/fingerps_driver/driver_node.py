"""driver_node: switches the LEDs over serial, captures and tags bursts, publishes them.

Thin ROS adapter: parameters, QoS, message conversion; the sequencing is
``fingerps_driver.burst.capture_burst`` and the board protocol ``fingerps_driver.led_board``.

With ``port`` = ``sim`` (the default) the node starts the board emulator on a real
pseudo-terminal in this process and drives it through pyserial exactly as it would drive the
real board; the simulated camera renders whatever LEDs the emulator has actually lit.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from fingerps_driver.board_emulator import BoardEmulator
from fingerps_driver.burst import BurstResult, CapturedFrame, capture_burst
from fingerps_driver.camera import Camera, SimulatedCamera
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.led_board import BoardError, LedBoard
from fingerps_driver.simulation import Reflectance, RigConfig, Scene, SimulatedRig
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_recon import qos, topics
from fingerps_recon.image_conversion import array_to_image
from fingerps_recon.node_runner import StartupError, run_node
from fingerps_recon.parameters import ParameterChecks, descriptor, one_of

SIM_PORT = "sim"
DARK_LED = TaggedFrame.LED_DARK


@dataclass
class _Counters:
    ok: int = 0
    failed: int = 0
    last_error: str = ""
    last_burst_ms: float = 0.0


def _stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class DriverNode(Node):
    """Captures bursts on demand (service) or continuously (``rate`` > 0)."""

    def __init__(self) -> None:
        super().__init__("driver", namespace=topics.NAMESPACE)
        self._checks = ParameterChecks(self)
        self._checks.add("camera", one_of("sim"))
        self._checks.add("sim.scene", one_of(*(s.value for s in Scene)))
        self._checks.add("sim.reflectance", one_of(*(r.value for r in Reflectance)))
        self._checks.add("sim.bit_depth", lambda v: None if v in (8, 12) else "must be 8 or 12")
        p = self.declare_parameter
        p("port", SIM_PORT, descriptor(
            "Serial device of the LED board, or 'sim' for the built-in board emulator on a "
            "pseudo-terminal", read_only=True))
        p("baudrate", 115200, descriptor("Serial baud rate", min_value=1200,
                                         max_value=4_000_000, integer=True, read_only=True))
        p("camera", "sim", descriptor("Camera backend: 'sim' (the simulated rig)",
                                      read_only=True))
        p("led_count", 7, descriptor("Number of LEDs on the board", min_value=3,
                                     max_value=16, integer=True, read_only=True))
        p("exposure_time", 0.01, descriptor("Exposure time per frame, seconds",
                                            min_value=1e-5, max_value=1.0))
        p("led_level", 1.0, descriptor("Relative LED drive level, 0..1", min_value=0.0,
                                       max_value=1.0))
        p("rate", 0.0, descriptor(
            "Continuous capture rate in bursts per second; 0 = only on request",
            min_value=0.0, max_value=30.0))
        p("with_dark_frame", False, descriptor(
            "Add an all-LEDs-off frame to continuous bursts (ambient subtraction)"))
        p("frame_id", "fingerps_camera_optical_frame", descriptor(
            "TF frame of the camera's optical frame (REP-103)", read_only=True))
        p("camera_name", "fingerps_sim", descriptor("Camera name in CameraInfo/calibration",
                                                    read_only=True))
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

        self._checks.refuse_unknown_overrides(self)

        self._lock = threading.Lock()
        self._counters = _Counters()
        self._burst_id = 0
        self._emulator: BoardEmulator | None = None
        self._board: LedBoard | None = None
        self._camera: Camera | None = None
        self._closed = False
        self._open_hardware()

        self._pub_frames = self.create_publisher(TaggedFrame, topics.FRAMES, qos.SENSOR_QOS)
        self._pub_image = self.create_publisher(Image, topics.IMAGE_RAW, qos.SENSOR_QOS)
        self._pub_info = self.create_publisher(CameraInfo, topics.CAMERA_INFO, qos.SENSOR_QOS)
        self._pub_burst = self.create_publisher(Burst, topics.BURST, qos.BURST_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_service(CaptureBurst, topics.CAPTURE_BURST, self._on_capture)
        self.create_timer(1.0, self._publish_diagnostics)
        self._rate_timer = None
        self._apply_rate(self.get_parameter("rate").value)
        self.add_post_set_parameters_callback(self._after_set)
        self.get_logger().info(
            f"driver ready: board on {self._board.port if self._board else '?'}, "
            f"{self._led_count} LEDs, camera {self._camera.width}x{self._camera.height} "
            f"{self._camera.encoding}")

    # ------------------------------------------------------------------ set-up
    @property
    def _led_count(self) -> int:
        return int(self.get_parameter("led_count").value)

    def _open_hardware(self) -> None:
        port = str(self.get_parameter("port").value)
        if port == SIM_PORT:
            self._emulator = BoardEmulator(self._led_count)
            self._emulator.start()
            port = self._emulator.port
        self._board = LedBoard(port, baudrate=int(self.get_parameter("baudrate").value))
        try:
            self._board.open()
            info = self._board.info()
        except BoardError as exc:
            self._close_hardware()
            raise StartupError(
                f"cannot use the LED board: {exc} (or use port:=sim for the simulated "
                "rig)") from None
        if info.led_count < self._led_count:
            self._close_hardware()
            raise StartupError(
                f"the board on {port!r} has {info.led_count} LEDs but led_count is "
                f"{self._led_count}; set led_count to at most {info.led_count}")
        self._camera = self._make_sim_camera()
        self._camera.open()

    def _make_sim_camera(self) -> Camera:
        config = RigConfig(
            reflectance=Reflectance(self.get_parameter("sim.reflectance").value),
            bit_depth=int(self.get_parameter("sim.bit_depth").value))
        self._rig = SimulatedRig(config)
        if self._rig.led_count != self._led_count:
            raise StartupError(
                f"the simulated rig has {self._rig.led_count} LEDs; set led_count to that")
        rng = np.random.default_rng(int(self.get_parameter("sim.seed").value))
        emulator = self._emulator
        if emulator is None:
            raise StartupError("camera:=sim needs port:=sim (the simulated board)")

        def render(lit: tuple[int, ...] | list[int]) -> np.ndarray:
            scene = Scene(self.get_parameter("sim.scene").value)
            return self._rig.render(scene, list(lit), rng=rng)

        encoding = "mono8" if config.bit_depth == 8 else "mono16"
        return SimulatedCamera(render, emulator.lit_leds, width=config.width,
                               height=config.height, encoding=encoding)

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
        if self._emulator is not None:
            self._emulator.stop()

    def destroy_node(self) -> None:
        """Switch the LEDs off and close the board and camera (idempotent)."""
        if not self._closed:
            self._closed = True
            with self._lock:
                self._close_hardware()
        super().destroy_node()

    # ------------------------------------------------------------------ parameters
    def _after_set(self, parameters: list) -> None:
        for param in parameters:
            if param.name == "rate":
                self._apply_rate(param.value)

    def _apply_rate(self, rate: float) -> None:
        if self._rate_timer is not None:
            self.destroy_timer(self._rate_timer)
            self._rate_timer = None
        if rate > 0:
            self._rate_timer = self.create_timer(1.0 / rate, self._on_rate_timer)

    # ------------------------------------------------------------------ capture
    def _on_rate_timer(self) -> None:
        self.capture(with_dark=bool(self.get_parameter("with_dark_frame").value))

    def _on_capture(self, request: CaptureBurst.Request,
                    response: CaptureBurst.Response) -> CaptureBurst.Response:
        result, burst = self.capture(with_dark=request.with_dark_frame,
                                     publish=not request.response_only)
        response.success = result.ok
        response.message = "ok" if result.ok else result.reason
        if burst is not None:
            response.burst = burst
        return response

    def capture(self, *, with_dark: bool, publish: bool = True
                ) -> tuple[BurstResult, Burst | None]:
        """Capture one burst, publish it if asked; return the result and the message if whole."""
        with self._lock:
            if self._closed or self._board is None or self._camera is None:
                raise FingerpsDriverError("the driver is shutting down")
            self._burst_id += 1
            count = self._led_count
            result = capture_burst(
                self._board, self._camera, burst_id=self._burst_id,
                led_order=range(count),
                exposures_s=float(self.get_parameter("exposure_time").value),
                levels=float(self.get_parameter("led_level").value),
                with_dark=with_dark,
                expected_shape=(self._camera.height, self._camera.width))
        if not result.ok:
            self._counters.failed += 1
            self._counters.last_error = result.reason
            self.get_logger().warning(f"burst {result.burst_id} failed: {result.reason}")
            return result, None
        self._counters.ok += 1
        self._counters.last_burst_ms = result.duration_s * 1e3
        return result, self._publish(result, count, publish=publish)

    def _camera_info(self, header: Header) -> CameraInfo:
        k = self._rig.camera_matrix
        info = CameraInfo(header=header, width=self._camera.width, height=self._camera.height)
        info.distortion_model = "plumb_bob"
        info.d = [0.0] * 5
        info.k = [float(x) for x in k.reshape(-1)]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [float(k[0, 0]), 0.0, float(k[0, 2]), 0.0,
                  0.0, float(k[1, 1]), float(k[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0]
        return info

    def _tagged(self, frame: CapturedFrame, burst_id: int, count: int) -> TaggedFrame:
        header = Header(stamp=_stamp(frame.stamp_ns),
                        frame_id=str(self.get_parameter("frame_id").value))
        return TaggedFrame(
            header=header, burst_id=burst_id, led_index=frame.led_index, led_count=count,
            exposure_time=frame.exposure_s, led_intensity=frame.level,
            image=array_to_image(frame.image, encoding=self._camera.encoding, header=header))

    def _publish(self, result: BurstResult, count: int, *, publish: bool) -> Burst:
        tagged = [self._tagged(f, result.burst_id, count) for f in result.frames]
        for msg in tagged if publish else ():
            self._pub_frames.publish(msg)
            self._pub_image.publish(msg.image)
        last = tagged[-1].header
        info = self._camera_info(last)
        burst = Burst(header=last, burst_id=result.burst_id, frames=tagged, camera_info=info)
        if result.dark is not None:
            burst.has_dark_frame = True
            burst.dark_frame = self._tagged(result.dark, result.burst_id, count)
        if publish:
            self._pub_info.publish(info)
            self._pub_burst.publish(burst)
        return burst

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        c = self._counters
        status = DiagnosticStatus(
            name=f"{self.get_name()}: bursts", hardware_id=str(self.get_parameter("port").value))
        status.level = DiagnosticStatus.OK if not c.last_error else DiagnosticStatus.WARN
        status.message = "capturing" if not c.last_error else f"last error: {c.last_error}"
        status.values = [KeyValue(key="bursts_ok", value=str(c.ok)),
                         KeyValue(key="bursts_failed", value=str(c.failed)),
                         KeyValue(key="last_burst_ms", value=f"{c.last_burst_ms:.1f}"),
                         KeyValue(key="last_error", value=c.last_error)]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_driver driver_node``."""
    return run_node(DriverNode, args=args, name="driver_node",
                    expected_errors=(FingerpsDriverError,))


if __name__ == "__main__":
    raise SystemExit(main())
