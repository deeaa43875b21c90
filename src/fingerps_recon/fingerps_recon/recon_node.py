"""recon_node: complete bursts in; normals, normal map, depth and a point cloud out.

Thin ROS adapter around ``fingerps_recon.pipeline.reconstruct_prepared``. The burst
callback only enqueues; a worker thread reconstructs, so a slow reconstruction never blocks
intake. The queue is bounded and drops the oldest burst, and the drops are counted. The
worker first warms the compiled kernels (``/diagnostics`` says ``ready`` once it has), and
prepares the calibration for the bursts' camera once, when the calibration, the
camera_info or the image size changes (:class:`PreparedCalibrations`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon import qos, topics
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.frames import optical_to_ps, ps_to_optical
from fingerps_recon.image_conversion import array_to_image, image_to_array, images_to_array
from fingerps_recon.kernel_threads import available_cores, set_thread_limit, thread_limit
from fingerps_recon.kernel_warm_up import warm_up_kernels
from fingerps_recon.node_runner import run_node
from fingerps_recon.normal_map import normal_map_rgb
from fingerps_recon.parameters import ParameterChecks, descriptor, one_of
from fingerps_recon.pipeline import (
    Model,
    PreparedCalibration,
    Projection,
    Reconstruction,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.point_cloud_conversion import points_to_cloud

_FULL_SCALE = {"mono8": 255.0, "mono16": 4095.0}


class ReconNode(Node):
    """Reconstructs every complete burst with the calibration in force."""

    def __init__(self) -> None:
        super().__init__("recon", namespace=topics.NAMESPACE)
        self._checks = ParameterChecks(self)
        self._checks.add("w", lambda v: None if v % 2 == 1 else "must be odd")
        self._checks.add("model", one_of(*(m.value for m in Model)))
        self._checks.add("projection", one_of(*(m.value for m in Projection)))
        p = self.declare_parameter
        p("model", Model.HK.value, descriptor(
            "Reflectance model of the normals: hk (the paper's simplified Hanrahan-Krueger "
            "skin model, initialised from lambert) or lambert (Lambertian photometric "
            "stereo)"))
        p("projection", Projection.PERSPECTIVE.value, descriptor(
            "Camera model of the views, the integration and the points: perspective (from "
            "the burst's camera_info) or orthographic"))
        p("hk_iterations", 5, descriptor(
            "Levenberg-Marquardt iterations of the HK solver", min_value=1, max_value=100,
            integer=True))
        p("threads", 0, descriptor(
            "Threads of the per-pixel solvers; 0 = every core. On a machine whose other cores "
            "are busy (driver, recorder) fewer threads can finish a burst sooner",
            min_value=0, max_value=256, integer=True))
        p("queue_depth", 2, descriptor(
            "Bursts waiting for reconstruction; the oldest is dropped beyond this",
            min_value=1, max_value=100, integer=True, read_only=True))
        p("mask_threshold", 0.15, descriptor(
            "Finger mask: fraction of the brightest level a pixel must exceed",
            min_value=0.01, max_value=0.9))
        p("enhance", True, descriptor(
            "Publish the normal map after ridge enhancement (paper Eq. 12); the normals "
            "topic always carries the unenhanced normals"))
        p("w", 7, descriptor("Ridge enhancement patch size (odd), pixels", min_value=3,
                             max_value=51, integer=True))
        p("k", 2.5, descriptor("Ridge enhancement gain", min_value=0.0, max_value=20.0))
        p("working_distance", 0.09, descriptor(
            "Camera-to-finger distance along the optical axis, metres (metric scale of "
            "depth)", min_value=0.005, max_value=2.0))
        p("mono16_full_scale", 4095.0, descriptor(
            "Largest value of a mono16 image (4095 for 12-bit sensors)", min_value=1.0,
            max_value=65535.0))

        self._checks.refuse_unknown_overrides(self)
        set_thread_limit(int(self.get_parameter("threads").value))
        self.add_post_set_parameters_callback(self._on_threads)

        # (burst, arrival time ns) waiting for the worker
        self._queue: deque[tuple[Burst, int]] = deque(
            maxlen=int(self.get_parameter("queue_depth").value))
        self._stages = StageTimes()
        self._cv = threading.Condition()
        self._stop = False
        self._dropped = 0
        self._done = 0
        self._failed = 0
        self._incomplete = 0
        self._last_error = ""
        self._lights: LightCalibration | None = None
        self._flat: FlatField | None = None
        self._flat_maps: np.ndarray | None = None
        self._camera: CameraInfo | None = None
        self._prepared = PreparedCalibrations()
        self._ready = False

        self.create_subscription(Burst, topics.BURST, self._on_burst, qos.BURST_QOS)
        self.create_subscription(LightCalibration, topics.LIGHT_CALIBRATION, self._on_lights,
                                 qos.CALIBRATION_QOS)
        self.create_subscription(FlatField, topics.FLAT_FIELD, self._on_flat,
                                 qos.CALIBRATION_QOS)
        self.create_subscription(CameraInfo, topics.CAMERA_INFO, self._on_camera_info,
                                 qos.SENSOR_QOS)
        self._pub_normals = self.create_publisher(Image, topics.NORMALS, qos.OUTPUT_QOS)
        self._pub_map = self.create_publisher(Image, topics.NORMAL_MAP, qos.OUTPUT_QOS)
        self._pub_depth = self.create_publisher(Image, topics.DEPTH, qos.OUTPUT_QOS)
        self._pub_albedo = self.create_publisher(Image, topics.ALBEDO, qos.OUTPUT_QOS)
        self._pub_points = self.create_publisher(PointCloud2, topics.POINTS, qos.OUTPUT_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_timer(1.0, self._publish_diagnostics)
        self._worker = threading.Thread(target=self._work, name="recon_worker")
        self._worker.start()
        self.get_logger().info("recon ready: waiting for a light calibration and bursts")

    def _on_threads(self, params: list) -> None:
        """A new ``threads`` value applies from the next burst on."""
        for param in params:
            if param.name == "threads":
                set_thread_limit(int(param.value))

    # ------------------------------------------------------------------ intake
    def _on_lights(self, msg: LightCalibration) -> None:
        self._lights = msg
        self.get_logger().info(f"light calibration received: {len(msg.directions)} LEDs")

    def _on_flat(self, msg: FlatField) -> None:
        try:
            maps = np.stack([image_to_array(m) for m in msg.maps]).astype(np.float32)
        except (FingerpsReconError, ValueError) as exc:
            self.get_logger().error(f"flat field refused: {exc}")
            return
        self._flat, self._flat_maps = msg, maps
        self.get_logger().info(f"flat field received: {maps.shape[0]} maps {maps.shape[1:]}")

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Kept so that the calibration is prepared for the camera before its first burst."""
        self._camera = msg

    def _on_burst(self, msg: Burst) -> None:
        with self._cv:
            if len(self._queue) == self._queue.maxlen:
                self._dropped += 1
                self.get_logger().warning(
                    f"reconstruction is behind: dropped the oldest burst ({self._dropped} so "
                    "far)", throttle_duration_sec=5.0)
            self._queue.append((msg, time.time_ns()))
            self._cv.notify()

    # ------------------------------------------------------------------ work
    def _warm_up(self) -> None:
        """Compile or load the kernels before the first burst (bursts wait meanwhile)."""
        self.get_logger().info("warming up the reconstruction kernels")
        warm = warm_up_kernels()
        self._ready = True
        self.get_logger().info(f"reconstruction ready: {warm.summary}")

    def _work(self) -> None:
        self._warm_up()
        while True:
            with self._cv:
                if not self._queue and not self._stop:
                    self._cv.wait(timeout=0.5)
                if self._stop:
                    return
                if not self._queue:
                    idle = True
                else:
                    idle = False
                    burst, arrival_ns = self._queue.popleft()
            if idle:
                self._prepare_ahead()
                continue
            try:
                self._reconstruct(burst, arrival_ns)
                self._done += 1
                self._last_error = ""
            except IncompleteBurstError as exc:
                self._incomplete += 1
                self._report(burst, exc)
            except FingerpsReconError as exc:
                self._failed += 1
                self._report(burst, exc)

    def _prepare_ahead(self) -> None:
        """While idle: prepare the calibration in force for the camera seen on camera_info
        (so that its first burst does not pay for it); the bursts prepare it otherwise."""
        lights, camera = self._lights, self._camera
        if lights is None or camera is None or camera.k[0] <= 0:
            return
        shape = (int(camera.height), int(camera.width))
        maps = self._flat_maps
        if maps is not None and maps.shape != (len(lights.directions), *shape):
            maps = None
        try:
            count = self._prepared.count
            self._prepared.get(lights, maps, np.asarray(camera.k, dtype=np.float64).reshape(3, 3),
                               shape, self._options())
            if self._prepared.count != count:
                self.get_logger().info(
                    f"calibration prepared for the {shape[1]}x{shape[0]} camera in "
                    f"{self._prepared.seconds * 1e3:.0f} ms"
                    + ("" if maps is not None else " (no flat field)"))
        except FingerpsReconError as exc:  # the first burst will say it again, counted
            self.get_logger().warning(f"calibration not prepared: {exc}",
                                      throttle_duration_sec=10.0)

    def _report(self, burst: Burst, exc: Exception) -> None:
        self._last_error = f"burst {burst.burst_id}: {exc}"
        self.get_logger().error(self._last_error, throttle_duration_sec=2.0)

    def _options(self) -> ReconstructionOptions:
        g = self.get_parameter
        return ReconstructionOptions(
            model=Model(g("model").value), hk_iterations=int(g("hk_iterations").value),
            projection=Projection(g("projection").value),
            mask_threshold=float(g("mask_threshold").value), enhance=bool(g("enhance").value),
            w=int(g("w").value), k=float(g("k").value),
            working_distance_m=float(g("working_distance").value))

    def _reconstruct(self, burst: Burst, arrival_ns: int) -> None:
        start_ns = time.time_ns()
        lights = self._lights
        if lights is None:
            raise FingerpsReconError(
                "no light calibration yet: call the calibrate_lights service (or start "
                "calib_node with a saved calibration) before sending bursts")
        maps = self._flat_maps
        made = reconstruct_burst(
            burst, lights, maps, options=self._options(),
            mono16_full_scale=float(self.get_parameter("mono16_full_scale").value),
            prepared=self._prepared)
        if maps is not None and not made.flat_field_used:
            self.get_logger().warning(
                f"flat field {maps.shape} does not fit the images {made.images.shape}; not "
                "used", throttle_duration_sec=10.0)
        result = made.result
        header = burst.header
        normals_optical = ps_to_optical(result.normals_ps, dtype=np.float32)
        self._pub_normals.publish(array_to_image(normals_optical, encoding="32FC3",
                                                 header=header))
        shown = result.enhanced_ps if result.enhanced_ps is not None else result.normals_ps
        self._pub_map.publish(array_to_image(normal_map_rgb(shown, mask=result.mask),
                                             encoding="rgb8", header=header))
        self._pub_depth.publish(array_to_image(result.depth_m, encoding="32FC1", header=header))
        self._pub_albedo.publish(array_to_image(result.albedo, encoding="32FC1", header=header))
        self._pub_points.publish(points_to_cloud(result.points_optical, result.point_albedo,
                                                 header=header))
        stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        self._stages.add(stamp_ns, arrival_ns, start_ns, result.timings_ms["total"],
                         time.time_ns())
        stages = ", ".join(f"{k} {v:.0f}" for k, v in result.timings_ms.items() if k != "total")
        self.get_logger().info(
            f"burst {burst.burst_id}: {result.mask.sum()} px, "
            f"{result.timings_ms['total']:.0f} ms ({stages} ms)", throttle_duration_sec=2.0)

    # ------------------------------------------------------------------ diagnostics, exit
    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name=f"{self.get_name()}: reconstruction")
        status.level = DiagnosticStatus.OK if not self._last_error else DiagnosticStatus.WARN
        status.message = self._last_error or (
            "ok" if self._ready else "warming up: compiling or loading the solver kernels")
        status.values = [KeyValue(key="ready", value=str(self._ready)),
                         KeyValue(key="threads", value=str(thread_limit())),
                         KeyValue(key="cores", value=str(available_cores())),
                         KeyValue(key="bursts_done", value=str(self._done)),
                         KeyValue(key="bursts_failed", value=str(self._failed)),
                         KeyValue(key="bursts_incomplete", value=str(self._incomplete)),
                         KeyValue(key="last_error", value=self._last_error),
                         KeyValue(key="bursts_dropped", value=str(self._dropped)),
                         KeyValue(key="calibrated", value=str(self._lights is not None)),
                         KeyValue(key="calibrations_prepared",
                                  value=str(self._prepared.count)),
                         *(KeyValue(key=key, value=f"{value:.1f}")
                           for key, value in self._stages.medians().items())]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)

    def destroy_node(self) -> None:
        """Stop the worker (it finishes the burst in hand) and destroy the node."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=60.0)
        super().destroy_node()


class StageTimes:
    """Where the recent bursts' time went, from the burst's stamp (its capture) to the
    outputs' publication: arrival here, waiting in the queue, reconstruction, publishing."""

    KEYS = ("capture_to_arrival_ms", "queue_wait_ms", "reconstruction_ms", "publish_ms",
            "capture_to_published_ms")

    def __init__(self, keep: int = 50) -> None:
        self._rows: deque[tuple[float, ...]] = deque(maxlen=keep)

    def add(self, stamp_ns: int, arrival_ns: int, start_ns: int, compute_ms: float,
            published_ns: int) -> None:
        """One burst: its stamp, arrival, start of work, reconstruction time and the moment
        its last output was published (wall-clock ns)."""
        ms = 1e-6
        work_ms = (published_ns - start_ns) * ms
        self._rows.append(((arrival_ns - stamp_ns) * ms, (start_ns - arrival_ns) * ms,
                           compute_ms, work_ms - compute_ms, (published_ns - stamp_ns) * ms))

    def medians(self) -> dict[str, float]:
        """Median of each stage over the recent bursts, ms (empty before the first)."""
        if not self._rows:
            return {}
        return dict(zip(self.KEYS, np.median(np.array(self._rows), axis=0), strict=True))


@dataclass(frozen=True)
class BurstReconstruction:
    """What :func:`reconstruct_burst` used and made."""

    result: Reconstruction
    images: np.ndarray            # (K, H, W) in LED order, as captured
    dark: np.ndarray | None       # (H, W) the burst's dark frame
    full_scale: float
    flat_field_used: bool


class PreparedCalibrations:
    """The calibration prepared for the bursts' camera (``prepare_calibration``): kept while
    the light calibration, the flat field, the camera matrix, the image size, the working
    distance and the projection stay the same; prepared again when one changes."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._held: tuple = ()  # the key's objects, kept alive so their ids stay theirs
        self._prepared: PreparedCalibration | None = None
        self.count = 0  # calibrations prepared so far
        self.seconds = 0.0  # time the last preparation took

    def get(self, lights: LightCalibration, flat_maps: np.ndarray | None,
            camera_matrix: np.ndarray, shape: tuple[int, int],
            options: ReconstructionOptions) -> PreparedCalibration:
        """The prepared calibration for these inputs, prepared now if they changed."""
        key = (id(lights), id(flat_maps), camera_matrix.tobytes(), tuple(shape),
               options.working_distance_m, options.projection)
        if key != self._key or self._prepared is None:
            start = time.perf_counter()
            count = len(lights.directions)
            intensities = np.asarray(lights.relative_intensities, dtype=np.float64)
            directions = np.array([[d.x, d.y, d.z] for d in lights.directions])
            leds = np.array([[p.x, p.y, p.z] for p in lights.led_positions])
            self._prepared = prepare_calibration(
                optical_to_ps(directions), camera_matrix=camera_matrix, shape=shape,
                intensities=intensities if intensities.size == count else None,
                portions=flat_maps,
                led_positions_optical=leds if len(leds) == count else None,
                options=options)
            self._key, self._held = key, (lights, flat_maps)
            self.count += 1
            self.seconds = time.perf_counter() - start
        return self._prepared


def reconstruct_burst(burst: Burst, lights: LightCalibration, flat_maps: np.ndarray | None,
                      *, options: ReconstructionOptions, mono16_full_scale: float = 4095.0,
                      prepared: PreparedCalibrations | None = None) -> BurstReconstruction:
    """Reconstruct a Burst message with a light calibration and flat-field maps (K, H, W)
    (None, or maps of another shape: not used), the calibration prepared by ``prepared``
    (kept there for the next burst) or afresh; raises ``FingerpsReconError``."""
    images, encoding = _burst_images(burst, len(lights.directions))
    full_scale = mono16_full_scale if encoding == "mono16" else _FULL_SCALE[encoding]
    maps = flat_maps if flat_maps is not None and flat_maps.shape == images.shape else None
    dark = image_to_array(burst.dark_frame.image) if burst.has_dark_frame else None
    k_matrix = np.asarray(burst.camera_info.k, dtype=np.float64).reshape(3, 3)
    if k_matrix[0, 0] <= 0:
        raise FingerpsReconError("the burst's camera_info has no intrinsics (fx <= 0)")
    start = time.perf_counter()
    cache = prepared or PreparedCalibrations()
    count = cache.count
    calibration = cache.get(lights, maps, k_matrix, images.shape[1:], options)
    result = reconstruct_prepared(images, calibration, full_scale=full_scale, dark=dark,
                                  options=options)
    if cache.count != count:  # prepared for this burst: say what it cost
        result.timings_ms["calibration"] = cache.seconds * 1e3
    result.timings_ms["total"] = (time.perf_counter() - start) * 1e3
    return BurstReconstruction(result, images, dark, full_scale, maps is not None)


class IncompleteBurstError(FingerpsReconError):
    """A burst lacks a frame of some LED (it is never reconstructed)."""


def _burst_images(burst: Burst, led_count: int) -> tuple[np.ndarray, str]:
    """The burst's images as (K, H, W) in LED order and their encoding; or an error saying
    what is wrong (a missing LED, mixed sizes or encodings, colour images)."""
    frames = sorted(burst.frames, key=lambda f: f.led_index)
    indices = [f.led_index for f in frames]
    if indices != list(range(led_count)):
        missing = sorted(set(range(led_count)) - set(indices))
        raise IncompleteBurstError(
            f"LEDs {indices} instead of 0..{led_count - 1}"
            + (f" (missing {missing})" if missing else "")
            + ": not reconstructed; the driver must publish whole bursts, or recalibrate if "
            "the LED count changed")
    encodings = {f.image.encoding for f in frames}
    sizes = {(f.image.height, f.image.width) for f in frames}
    if len(encodings) != 1 or len(sizes) != 1:
        raise FingerpsReconError(
            f"the burst mixes image encodings {sorted(encodings)} or sizes {sorted(sizes)}; "
            "every frame of a burst must come from one camera mode")
    encoding = encodings.pop()
    if encoding not in _FULL_SCALE:
        raise FingerpsReconError(
            f"the burst's images are {encoding}; photometric stereo needs one grey level per "
            f"pixel: set the camera's pixel format to {' or '.join(_FULL_SCALE)}")
    return images_to_array([f.image for f in frames]), encoding


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon recon_node``."""
    return run_node(ReconNode, args=args, name="recon_node",
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
