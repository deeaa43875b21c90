"""recon_node: complete bursts in; normals, normal map, depth and a point cloud out.

Thin ROS adapter around ``fingerps_recon.photometric.pipeline.reconstruct_prepared``. The burst
callback only enqueues; a worker thread reconstructs, so a slow reconstruction never blocks
intake. The queue is bounded and drops the oldest burst, and the drops are counted. The
worker first warms the compiled kernels (``/diagnostics`` says ``ready`` once it has), and
prepares the calibration for the bursts' camera once, when the calibration, the
camera_info or the image size changes (:class:`PreparedCalibrations`).

Every message is survived: a burst beyond the size bounds (``max_image_width``,
``max_image_height``, ``max_burst_frames``) is refused on arrival, before it is queued; a
light calibration or flat field that cannot determine normals is refused on arrival (the
previous one stays in force); anything else a burst raises, expected or not, is logged in
one line naming the burst and counted, and the worker goes on with the next burst. An
empty reconstruction is a failure, not a done burst. ``/diagnostics`` is WARN while one of
the last ``health_window`` bursts failed (or a refused calibration was not replaced), ERROR
when all of them failed, OK once good bursts flow again.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical
from fingerps_recon.photometric.kernel_threads import (
    available_cores,
    set_thread_limit,
    thread_limit,
)
from fingerps_recon.photometric.kernel_warm_up import warm_up_kernels
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import (
    Model,
    NoFingerError,
    PreparedCalibration,
    Projection,
    Reconstruction,
    ReconstructionOptions,
    check_calibration,
    check_portions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.surface.rolled_print import RolledPrint, RolledPrintError, rolled_print
from fingerps_ros import qos, topics
from fingerps_ros.compressed_topics import CompressedTopics
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image, image_to_array, images_to_array
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import ParameterChecks, descriptor, one_of
from fingerps_ros.point_cloud_conversion import points_to_cloud

_FULL_SCALE = {"mono8": 255.0, "mono16": 4095.0}
# Outcome of a burst, for the diagnostic level.
_OK, _WARN, _BAD = 0, 1, 2


class ReconNode(Node):
    """Reconstructs every complete burst with the calibration in force."""

    def __init__(self, **node_options: object) -> None:
        """``node_options``: rclpy ``Node`` keywords (a test gives its ``context``)."""
        super().__init__("recon", namespace=topics.NAMESPACE, **node_options)
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
        p("fingerprint", False, descriptor(
            "Also publish the rolled-equivalent 500 ppi print of every burst on 'fingerprint' "
            "(mono8, ridges dark; ~50 ms a burst on top of the reconstruction, so off by "
            "default; the Scan action always makes one)"))
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
        p("max_image_width", BurstLimits.max_width, descriptor(
            "Widest image accepted (bursts, dark frames, flat-field maps, the camera_info "
            "the calibration is prepared for), pixels; wider ones are refused on arrival",
            min_value=1, max_value=65535, integer=True))
        p("max_image_height", BurstLimits.max_height, descriptor(
            "Tallest image accepted, pixels (as max_image_width)", min_value=1,
            max_value=65535, integer=True))
        p("max_burst_frames", BurstLimits.max_frames, descriptor(
            "Most frames a burst (or flat-field maps a flat field) may carry; more are "
            "refused on arrival", min_value=3, max_value=256, integer=True))
        p("health_window", 5, descriptor(
            "Recent bursts /diagnostics judges: WARN while one of them failed, ERROR when "
            "all of them did", min_value=1, max_value=1000, integer=True, read_only=True))
        # image_transport-style companions (normal_map/compressed, fingerprint/compressed,
        # depth/compressedDepth): encoded only while subscribed (compressed_topics.py)
        self._compressed = {
            name: CompressedTopics(self, name, qos.OUTPUT_QOS, self._checks,
                                   depth=name == topics.DEPTH)
            for name in (topics.NORMAL_MAP, topics.FINGERPRINT, topics.DEPTH)}

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
        self._rejected = 0
        self._unexpected = 0
        self._calibrations_refused = 0
        self._flat_unused = 0
        self._last_error = ""
        self._last_problem = ""
        # outcome of each recent burst: OK, WARN (no finger, flat field not used) or BAD
        self._outcomes: deque[int] = deque(
            maxlen=int(self.get_parameter("health_window").value))
        self._refused: dict[str, str] = {}  # calibration kind -> why its last one was refused
        self._log_gate = LogGate()
        self._lights: LightCalibration | None = None
        self._flat: FlatField | None = None
        self._flat_maps: np.ndarray | None = None
        self._camera: CameraInfo | None = None
        self._prepared = PreparedCalibrations()
        self._ready = False

        guarded = self._guarded
        self.create_subscription(Burst, topics.BURST, guarded("burst", self._on_burst),
                                 qos.BURST_QOS)
        self.create_subscription(LightCalibration, topics.LIGHT_CALIBRATION,
                                 guarded("light calibration", self._on_lights),
                                 qos.CALIBRATION_QOS)
        self.create_subscription(FlatField, topics.FLAT_FIELD,
                                 guarded("flat field", self._on_flat), qos.CALIBRATION_QOS)
        self.create_subscription(CameraInfo, topics.CAMERA_INFO,
                                 guarded("camera_info", self._on_camera_info), qos.SENSOR_QOS)
        self._pub_normals = self.create_publisher(Image, topics.NORMALS, qos.OUTPUT_QOS)
        self._pub_map = self.create_publisher(Image, topics.NORMAL_MAP, qos.OUTPUT_QOS)
        self._pub_depth = self.create_publisher(Image, topics.DEPTH, qos.OUTPUT_QOS)
        self._pub_albedo = self.create_publisher(Image, topics.ALBEDO, qos.OUTPUT_QOS)
        self._pub_points = self.create_publisher(PointCloud2, topics.POINTS, qos.OUTPUT_QOS)
        self._pub_print = self.create_publisher(Image, topics.FINGERPRINT, qos.OUTPUT_QOS)
        self._prints_made = 0
        self._prints_rejected = 0
        self._last_print_problem = ""
        self._print_ms: deque[float] = deque(maxlen=50)
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_timer(1.0, guarded("diagnostics", self._publish_diagnostics))
        self._worker = threading.Thread(target=self._work, name="recon_worker")
        self._worker.start()
        self.get_logger().info("recon ready: waiting for a light calibration and bursts")

    def _on_threads(self, params: list) -> None:
        """A new ``threads`` value applies from the next burst on."""
        for param in params:
            if param.name == "threads":
                set_thread_limit(int(param.value))

    def _limits(self) -> BurstLimits:
        g = self.get_parameter
        return BurstLimits(max_width=int(g("max_image_width").value),
                           max_height=int(g("max_image_height").value),
                           max_frames=int(g("max_burst_frames").value))

    def _guarded(self, what: str, callback: Callable[..., None]) -> Callable[..., None]:
        """``callback`` that logs and counts what it raises instead of ending the node."""
        def run(*args: object) -> None:
            try:
                callback(*args)
            except Exception as exc:  # a callback must never end the node
                self._unexpected += 1
                self._last_problem = f"{what}: unexpected {_one_line(exc)}"
                self.get_logger().error(self._last_problem, throttle_duration_sec=2.0)
        return run

    # ------------------------------------------------------------------ intake
    def _refuse(self, kind: str, reason: str) -> None:
        """A calibration message refused on arrival: counted, and WARN until replaced."""
        self._calibrations_refused += 1
        self._refused[kind] = reason
        self._last_problem = f"{kind} refused: {reason}"
        held = self._lights if kind == "light calibration" else self._flat
        self.get_logger().error(f"{self._last_problem}; "
                                + ("the previous one stays in force" if held is not None
                                   else "none is in force"))

    def _on_lights(self, msg: LightCalibration) -> None:
        try:
            check_light_calibration(msg)
        except FingerpsError as exc:
            self._refuse("light calibration", str(exc))
            return
        self._lights = msg
        self._refused.pop("light calibration", None)
        self.get_logger().info(f"light calibration received: {len(msg.directions)} LEDs")

    def _on_flat(self, msg: FlatField) -> None:
        try:
            maps = flat_field_maps(msg, self._limits())
        except FingerpsError as exc:
            self._refuse("flat field", str(exc))
            return
        self._flat, self._flat_maps = msg, maps
        self._refused.pop("flat field", None)
        self.get_logger().info(f"flat field received: {maps.shape[0]} maps {maps.shape[1:]}")

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Kept so that the calibration is prepared for the camera before its first burst."""
        self._camera = msg

    def _on_burst(self, msg: Burst) -> None:
        try:  # refused before it takes a place in the queue
            check_burst_size(msg, self._limits())
        except FingerpsError as exc:
            self._rejected += 1
            self._note(_BAD, msg, exc)
            return
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
        try:
            warm = warm_up_kernels()
        except Exception as exc:  # the worker must never die: the first burst compiles them
            self._unexpected += 1
            self.get_logger().error(f"warming up the kernels failed: {_one_line(exc)}; the "
                                    "first bursts compile them instead")
            return
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
                try:
                    self._prepare_ahead()
                except Exception as exc:  # the worker must never die
                    self._unexpected += 1
                    self.get_logger().error(
                        f"preparing the calibration: unexpected {_one_line(exc)}",
                        throttle_duration_sec=10.0)
                continue
            try:
                self._reconstruct(burst, arrival_ns)
            except IncompleteBurstError as exc:
                self._incomplete += 1
                self._note(_BAD, burst, exc)
            except NoFingerError as exc:
                self._failed += 1
                self._note(_WARN, burst, exc)
            except FingerpsError as exc:
                self._failed += 1
                self._note(_BAD, burst, exc)
            except Exception as exc:  # the worker must never die
                self._failed += 1
                self._unexpected += 1
                self._note(_BAD, burst, exc, unexpected=True)

    def _prepare_ahead(self) -> None:
        """While idle: prepare the calibration in force for the camera seen on camera_info
        (so that its first burst does not pay for it); the bursts prepare it otherwise."""
        lights, camera = self._lights, self._camera
        if lights is None or camera is None or not camera.k[0] > 0:
            return
        shape = (int(camera.height), int(camera.width))
        limits = self._limits()
        if not (1 <= shape[0] <= limits.max_height and 1 <= shape[1] <= limits.max_width):
            return  # a camera_info of no size or beyond the bounds: its bursts will say so
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
        except FingerpsError as exc:  # the first burst will say it again, counted
            self.get_logger().warning(f"calibration not prepared: {exc}",
                                      throttle_duration_sec=10.0)

    def _note(self, outcome: int, burst: Burst, exc: Exception, *,
              unexpected: bool = False) -> None:
        """One burst not reconstructed: remembered for the diagnostic level, logged in one
        line naming the burst and the problem (no traceback)."""
        problem = f"unexpected {_one_line(exc)}" if unexpected else str(exc)
        self._last_error = f"burst {burst.burst_id}: {problem}"
        self._last_problem = self._last_error
        self._outcomes.append(outcome)
        if self._log_gate.opens(problem):
            self.get_logger().error(self._last_error)

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
            refused = self._refused.get("light calibration")
            raise FingerpsReconError(
                "no light calibration yet"
                + (f" (the last one was refused: {refused})" if refused else "")
                + ": call the calibrate_lights service (or start calib_node with a saved "
                "calibration) before sending bursts")
        maps = self._flat_maps
        made = reconstruct_burst(
            burst, lights, maps, options=self._options(),
            mono16_full_scale=float(self.get_parameter("mono16_full_scale").value),
            prepared=self._prepared, limits=self._limits())
        outcome = _OK
        if maps is not None and not made.flat_field_used:
            outcome = _WARN
            self._flat_unused += 1
            self._last_problem = (f"burst {burst.burst_id}: flat field {maps.shape} does not "
                                  f"fit the images {made.images.shape}; not used")
            self.get_logger().warning(self._last_problem, throttle_duration_sec=10.0)
        result = made.result
        header = burst.header
        normals_optical = ps_to_optical(result.normals_ps, dtype=np.float32)
        self._pub_normals.publish(array_to_image(normals_optical, encoding="32FC3",
                                                 header=header))
        shown = result.enhanced_ps if result.enhanced_ps is not None else result.normals_ps
        rgb = normal_map_rgb(shown, mask=result.mask)
        self._pub_map.publish(array_to_image(rgb, encoding="rgb8", header=header))
        self._pub_depth.publish(array_to_image(result.depth_m, encoding="32FC1", header=header))
        self._pub_albedo.publish(array_to_image(result.albedo, encoding="32FC1", header=header))
        self._pub_points.publish(points_to_cloud(result.points_optical, result.point_albedo,
                                                 header=header))
        if self.get_parameter("fingerprint").value and not self._publish_fingerprint(made,
                                                                                     burst):
            outcome = _WARN
        self._compressed[topics.NORMAL_MAP].publish(rgb, "rgb8", header)  # after the raw ones
        self._compressed[topics.DEPTH].publish(result.depth_m, "32FC1", header)
        stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        self._stages.add(stamp_ns, arrival_ns, start_ns, result.timings_ms["total"],
                         time.time_ns())
        self._done += 1
        self._last_error = ""
        self._outcomes.append(outcome)
        stages = ", ".join(f"{k} {v:.0f}" for k, v in result.timings_ms.items() if k != "total")
        self.get_logger().info(
            f"burst {burst.burst_id}: {result.mask.sum()} px, "
            f"{result.timings_ms['total']:.0f} ms ({stages} ms)", throttle_duration_sec=2.0)

    def _publish_fingerprint(self, made: BurstReconstruction, burst: Burst) -> bool:
        """Publish the burst's rolled print; False (logged, counted) when it cannot be made."""
        start = time.perf_counter()
        try:
            made_print = made.fingerprint()
        except RolledPrintError as exc:
            self._prints_rejected += 1
            self._last_print_problem = f"burst {burst.burst_id}: no fingerprint: {exc}"
            self._last_problem = self._last_print_problem
            self.get_logger().warning(self._last_print_problem, throttle_duration_sec=5.0)
            return False
        self._print_ms.append((time.perf_counter() - start) * 1e3)
        header = Header(stamp=burst.header.stamp, frame_id=topics.FINGERPRINT_FRAME)
        self._pub_print.publish(array_to_image(made_print.image, encoding="mono8",
                                               header=header))
        self._compressed[topics.FINGERPRINT].publish(made_print.image, "mono8", header)
        self._prints_made += 1
        return True

    # ------------------------------------------------------------------ diagnostics, exit
    def _level(self) -> tuple[bytes, str]:
        """The diagnostic level and message: ERROR when every one of the last
        ``health_window`` bursts failed, WARN while one of them failed or did without the
        flat field, or a refused calibration was not replaced; OK otherwise."""
        outcomes = list(self._outcomes)
        bad = outcomes.count(_BAD)
        if outcomes and bad == len(outcomes) == self._outcomes.maxlen:
            return DiagnosticStatus.ERROR, (
                f"the last {bad} bursts all failed; last: {self._last_problem}")
        if self._refused:
            return DiagnosticStatus.WARN, "; ".join(
                f"{kind} refused: {reason}" for kind, reason in self._refused.items())
        if self._last_error:
            return DiagnosticStatus.WARN, self._last_error
        if any(o != _OK for o in outcomes):
            return DiagnosticStatus.WARN, (
                f"{len(outcomes) - outcomes.count(_OK)} of the last {len(outcomes)} bursts "
                f"failed or were degraded; last: {self._last_problem}")
        return DiagnosticStatus.OK, (
            "ok" if self._ready else "warming up: compiling or loading the solver kernels")

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name=f"{self.get_name()}: reconstruction")
        status.level, status.message = self._level()
        status.values = [KeyValue(key="ready", value=str(self._ready)),
                         KeyValue(key="threads", value=str(thread_limit())),
                         KeyValue(key="cores", value=str(available_cores())),
                         KeyValue(key="bursts_done", value=str(self._done)),
                         KeyValue(key="bursts_failed", value=str(self._failed)),
                         KeyValue(key="bursts_incomplete", value=str(self._incomplete)),
                         KeyValue(key="bursts_rejected", value=str(self._rejected)),
                         KeyValue(key="unexpected_errors", value=str(self._unexpected)),
                         KeyValue(key="calibrations_refused",
                                  value=str(self._calibrations_refused)),
                         KeyValue(key="bursts_without_flat_field",
                                  value=str(self._flat_unused)),
                         KeyValue(key="last_error", value=self._last_error),
                         KeyValue(key="last_problem", value=self._last_problem),
                         KeyValue(key="fingerprints_made", value=str(self._prints_made)),
                         KeyValue(key="fingerprints_rejected", value=str(self._prints_rejected)),
                         KeyValue(key="last_fingerprint_problem",
                                  value=self._last_print_problem),
                         KeyValue(key="fingerprint_ms_median", value=(
                             f"{float(np.median(self._print_ms)):.1f}" if self._print_ms
                             else "")),
                         KeyValue(key="bursts_dropped", value=str(self._dropped)),
                         KeyValue(key="compressed_failures", value=str(
                             sum(c.failures for c in self._compressed.values()))),
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


class LogGate:
    """Whether to log a problem: every new one, the same one again at most every
    ``period_s`` (a stream of identical bad bursts gives one line per period, a mix of
    different problems one line each)."""

    def __init__(self, period_s: float = 5.0, keep: int = 64) -> None:
        self._period_s = period_s
        self._keep = keep
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def opens(self, problem: str) -> bool:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(problem)
            if last is not None and now - last < self._period_s:
                return False
            if len(self._last) >= self._keep:
                self._last = {p: t for p, t in self._last.items()
                              if now - t < self._period_s}
            self._last[problem] = now
            return True


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
    camera_matrix: np.ndarray     # (3, 3) K of the burst's camera_info

    def fingerprint(self) -> RolledPrint:
        """The rolled-equivalent 500 ppi print of this reconstruction
        (`fingerps_recon.surface.rolled_print`); raises `RolledPrintError` with the reason when the
        reconstruction covers too little of the finger or is too noisy or strained."""
        result = self.result
        return rolled_print(result.depth_m, mask=result.mask, camera_matrix=self.camera_matrix,
                            normals_ps=result.normals_ps)


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
            directions, intensities, leds = _calibration_arrays(lights)
            self._prepared = prepare_calibration(
                directions, camera_matrix=camera_matrix, shape=shape,
                intensities=intensities, portions=flat_maps, led_positions_optical=leds,
                options=options)
            self._key, self._held = key, (lights, flat_maps)
            self.count += 1
            self.seconds = time.perf_counter() - start
        return self._prepared


def reconstruct_burst(burst: Burst, lights: LightCalibration, flat_maps: np.ndarray | None,
                      *, options: ReconstructionOptions, mono16_full_scale: float = 4095.0,
                      prepared: PreparedCalibrations | None = None,
                      limits: BurstLimits | None = None) -> BurstReconstruction:
    """Reconstruct a Burst message with a light calibration and flat-field maps (K, H, W)
    (None, or maps of another shape: not used), the calibration prepared by ``prepared``
    (kept there for the next burst) or afresh; raises ``FingerpsReconError`` on any burst or
    calibration it cannot reconstruct: beyond ``limits`` (:func:`check_burst_size`),
    malformed, a dark frame of another encoding or size, a degenerate calibration
    (``pipeline.check_calibration``), or an empty result (:class:`EmptyReconstructionError`).
    """
    check_burst_size(burst, limits or BurstLimits())
    images, encoding = _burst_images(burst, len(lights.directions))
    full_scale = mono16_full_scale if encoding == "mono16" else _FULL_SCALE[encoding]
    maps = flat_maps if flat_maps is not None and flat_maps.shape == images.shape else None
    dark = None
    if burst.has_dark_frame:
        image = burst.dark_frame.image
        if image.encoding != encoding or (image.height, image.width) != images.shape[1:]:
            raise FingerpsReconError(
                f"the dark frame is {image.width}x{image.height} {image.encoding} but the "
                f"images are {images.shape[2]}x{images.shape[1]} {encoding}: it must come "
                "from the same camera mode")
        dark = image_to_array(image)
    k_matrix = np.asarray(burst.camera_info.k, dtype=np.float64).reshape(3, 3)
    if not k_matrix[0, 0] > 0:
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
    if not result.mask.any() or len(result.points_optical) == 0:
        raise EmptyReconstructionError(
            f"nothing reconstructed: {int(result.mask.sum())} pixels with a valid normal, "
            f"{len(result.points_optical)} points although the mask found a finger; check "
            "the light calibration (recalibrate the lights and the flat field)")
    return BurstReconstruction(result, images, dark, full_scale, maps is not None, k_matrix)


class IncompleteBurstError(FingerpsReconError):
    """A burst lacks a frame of some LED (it is never reconstructed)."""


class EmptyReconstructionError(FingerpsReconError):
    """A burst whose reconstruction has no valid normal or no point: not a done burst."""


@dataclass(frozen=True)
class BurstLimits:
    """Bounds on what a burst may carry (parameters max_image_width, max_image_height,
    max_burst_frames of recon_node)."""

    max_width: int = 4096
    max_height: int = 4096
    max_frames: int = 16


def check_burst_size(burst: Burst, limits: BurstLimits) -> None:
    """Raise ``FingerpsReconError`` if a burst carries more frames than ``limits`` allow, or
    an image (a frame, the dark or repeat frame) of no pixels or beyond the size bounds.
    Reads the messages' fields only: cheap enough for the subscription callback."""
    if len(burst.frames) > limits.max_frames:
        raise FingerpsReconError(
            f"{len(burst.frames)} frames, more than max_burst_frames {limits.max_frames}: "
            "refused; raise max_burst_frames if the rig really has that many LEDs")
    images = [f.image for f in burst.frames]
    images += [burst.dark_frame.image] if burst.has_dark_frame else []
    images += [burst.repeat_frame.image] if burst.has_repeat_frame else []
    for image in images:
        _check_image_size(image, limits, "image")


def _check_image_size(image: Image, limits: BurstLimits, what: str) -> None:
    width, height = int(image.width), int(image.height)
    if width < 1 or height < 1:
        raise FingerpsReconError(
            f"an {what} of {width}x{height} px: empty; check the camera's publisher")
    if width > limits.max_width or height > limits.max_height:
        raise FingerpsReconError(
            f"an {what} of {width}x{height} px, beyond max_image_width x max_image_height "
            f"{limits.max_width}x{limits.max_height}: refused; raise the bounds if the "
            "camera really is that large (memory and time grow with the pixels)")


def _calibration_arrays(lights: LightCalibration) -> tuple[
        np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Directions (K, 3) in the PS frame, relative intensities (K,) or None, LED positions
    (K, 3) in the optical frame or None, from a LightCalibration message."""
    directions = np.array([[d.x, d.y, d.z] for d in lights.directions],
                          dtype=np.float64).reshape(-1, 3)
    intensities = np.asarray(lights.relative_intensities, dtype=np.float64)
    leds = np.array([[p.x, p.y, p.z] for p in lights.led_positions],
                    dtype=np.float64).reshape(-1, 3)
    return (optical_to_ps(directions), intensities if intensities.size else None,
            leds if len(leds) else None)


def check_light_calibration(lights: LightCalibration) -> None:
    """Raise ``FingerpsReconError`` unless the message can determine normals (finite, unit,
    non-degenerate directions; finite positive intensities; finite LED positions, one per
    direction): ``pipeline.check_calibration`` on its arrays."""
    directions, intensities, leds = _calibration_arrays(lights)
    check_calibration(directions, intensities=intensities, led_positions_optical=leds)


def flat_field_maps(flat: FlatField, limits: BurstLimits) -> np.ndarray:
    """The portion maps (K, H, W) float32 of a FlatField message, or ``FingerpsReconError``
    if there are none or too many, they are not single-channel maps of one size within
    ``limits``, or not finite and positive (``pipeline.check_portions``)."""
    if not 1 <= len(flat.maps) <= limits.max_frames:
        raise FingerpsReconError(
            f"{len(flat.maps)} flat-field maps: give one per LED (at most max_burst_frames "
            f"{limits.max_frames})")
    for image in flat.maps:
        _check_image_size(image, limits, "flat-field map")
    maps = images_to_array(list(flat.maps))
    if maps.ndim != 3:
        raise FingerpsReconError(
            f"flat-field maps of {flat.maps[0].encoding}: they must have one channel (32FC1)")
    maps = maps.astype(np.float32)
    check_portions(maps)
    return maps


def _one_line(exc: BaseException) -> str:
    """``Type: message (at file.py:line)`` of an exception: one log line, no traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" (at {Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    message = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {message}{where}"


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
