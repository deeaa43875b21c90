"""scan_node: the Scan action - wait for a finger, capture still bursts, reconstruct, judge.

Thin ROS adapter for kiosks and robots. One goal at a time: a goal arriving while another
runs, or one with impossible values, is rejected at once; ROS 2's goal response carries no
text, so the reason is logged and published on ``scan/rejections`` (std_msgs/String).

A goal runs through three states (reported as feedback):

1. waiting for a finger: bursts with a dark frame, not published (``response_only``), each
   checked by ``finger_presence.detect_finger`` (its first LED's frame minus the dark
   frame) until a finger covers ``presence_min_coverage`` of the image;
2. capturing: a burst with a dark frame and the first LED repeated at its end
   (``repeat_first_led``), published on ``burst`` (so the recorder records it);
   ``burst_motion.estimate_motion`` compares the first LED's frame with its repeat, and a
   burst in which the finger moved more than ``max_motion_px`` is rejected, counted and
   retaken (at most ``max_retakes`` times); a burst without a finger goes back to 1;
3. reconstructing: ``recon_node.reconstruct_burst`` with the calibration in force (the
   transient-local calibration topics), then ``quality.quality_figures`` and
   ``quality.judge_quality``.

After ``bursts`` reconstructions the best (accepted before rejected, then fewer reasons,
then the smaller residual) is the result, with its verdict; the verdict is also published
on ``/diagnostics``. A cancel is honoured between steps (a burst in progress finishes; the
driver switches the LEDs off at the end of every burst). The overall ``timeout`` ends a goal
that found no finger, or no still one, in time (aborted, with the reason).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Header, String

from fingerps_msgs.action import Scan
from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_msgs.srv import CaptureBurst
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import Model, Projection, ReconstructionOptions
from fingerps_recon.recon_node import (
    BurstReconstruction,
    PreparedCalibrations,
    reconstruct_burst,
)
from fingerps_recon.scan.burst_motion import BurstMotion, estimate_motion
from fingerps_recon.scan.finger_presence import FingerPresence, detect_finger
from fingerps_recon.scan.quality import (
    QualityThresholds,
    QualityVerdict,
    judge_quality,
    quality_figures,
)
from fingerps_recon.surface.rolled_print import RolledPrintError
from fingerps_ros import qos, topics
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image, image_to_array
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import ParameterChecks, descriptor, one_of
from fingerps_ros.point_cloud_conversion import points_to_cloud

SCAN = "scan"                       # fingerps_msgs/action/Scan
SCAN_REJECTIONS = "scan/rejections"  # std_msgs/String: why a goal was rejected
MAX_BURSTS = 20
STATE_NAMES = {Scan.Feedback.WAITING_FOR_FINGER: "waiting_for_finger",
               Scan.Feedback.CAPTURING: "capturing",
               Scan.Feedback.RECONSTRUCTING: "reconstructing"}
_FULL_SCALE = {"mono8": 255.0, "mono16": 4095.0}

# Parameters a goal may override (``Scan.Goal.overrides``): reconstruction and judgement.
GOAL_PARAMETERS = (
    "model", "hk_iterations", "projection", "mask_threshold", "enhance", "w", "k",
    "working_distance", "presence_threshold", "presence_min_coverage", "max_motion_px",
    "max_retakes", "min_coverage", "max_saturated_fraction", "max_dark_fraction",
    "min_ridge_visibility", "max_residual")


@dataclass(frozen=True)
class ScanSettings:
    """Everything one goal runs with (the node's parameters with the goal's overrides)."""

    bursts: int
    timeout_s: float
    options: ReconstructionOptions
    thresholds: QualityThresholds
    presence_threshold: float
    presence_min_coverage: float
    max_retakes: int


@dataclass
class _Best:
    made: BurstReconstruction
    burst: Burst
    verdict: QualityVerdict

    def rank(self) -> tuple:
        residual = self.verdict.figures.residual
        return (not self.verdict.accepted, len(self.verdict.reasons),
                residual if math.isfinite(residual) else math.inf)


class ScanAbortedError(Exception):
    """The goal cannot go on; the message says why and what to do."""


class ScanNode(Node):
    """Serves the Scan action over the driver's capture_burst service."""

    def __init__(self) -> None:
        super().__init__("scan", namespace=topics.NAMESPACE)
        self._declare_parameters()
        self._checks.refuse_unknown_overrides(self)
        self._group = ReentrantCallbackGroup()
        self._lock = threading.Lock()
        self._busy = False
        self._lights: LightCalibration | None = None
        self._flat_maps: np.ndarray | None = None
        self._prepared = PreparedCalibrations()
        self._last_verdict: QualityVerdict | None = None
        self._counts = {"goals": 0, "rejected_goals": 0, "succeeded": 0, "aborted": 0,
                        "cancelled": 0, "bursts_rejected_motion": 0}
        self.create_subscription(LightCalibration, topics.LIGHT_CALIBRATION, self._on_lights,
                                 qos.CALIBRATION_QOS, callback_group=self._group)
        self.create_subscription(FlatField, topics.FLAT_FIELD, self._on_flat,
                                 qos.CALIBRATION_QOS, callback_group=self._group)
        self._capture = self.create_client(CaptureBurst, topics.CAPTURE_BURST,
                                           callback_group=self._group)
        recorder = str(self.get_parameter("recorder").value)
        self._recorder_params = (self.create_client(
            GetParameters, f"{recorder}/get_parameters", callback_group=self._group)
            if recorder else None)
        self._pub_rejections = self.create_publisher(String, SCAN_REJECTIONS, 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self.create_timer(1.0, self._publish_diagnostics, callback_group=self._group)
        self._server = ActionServer(
            self, Scan, SCAN, execute_callback=self._execute, goal_callback=self._on_goal,
            cancel_callback=lambda _goal: CancelResponse.ACCEPT, callback_group=self._group)
        self.get_logger().info("scan ready: waiting for a light calibration and goals")

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        checks = self._checks = ParameterChecks(self)
        checks.add("w", lambda v: None if v % 2 == 1 else "must be odd")
        checks.add("model", one_of(*(m.value for m in Model)))
        checks.add("projection", one_of(*(m.value for m in Projection)))
        p = self.declare_parameter
        p("model", Model.HK.value, descriptor(
            "Reflectance model: hk (the paper's skin model; the most accurate normals) or "
            "lambert (faster); a goal's model field overrides it"))
        p("projection", Projection.PERSPECTIVE.value, descriptor(
            "Camera model: perspective (the burst's camera_info) or orthographic"))
        p("hk_iterations", 5, descriptor("Levenberg-Marquardt iterations of the HK solver",
                                         min_value=1, max_value=100, integer=True))
        p("mask_threshold", 0.15, descriptor(
            "Finger mask: fraction of the brightest level a pixel must exceed",
            min_value=0.01, max_value=0.9))
        p("enhance", True, descriptor("Ridge enhancement (paper Eq. 12) of the normal map"))
        p("w", 7, descriptor("Ridge enhancement patch size (odd), pixels", min_value=3,
                             max_value=51, integer=True))
        p("k", 2.5, descriptor("Ridge enhancement gain", min_value=0.0, max_value=20.0))
        p("working_distance", 0.09, descriptor(
            "Camera-to-finger distance, metres (metric scale of depth)", min_value=0.005,
            max_value=2.0))
        p("mono16_full_scale", 4095.0, descriptor(
            "Largest value of a mono16 image", min_value=1.0, max_value=65535.0))
        p("timeout", 30.0, descriptor(
            "Seconds a goal may take when it gives timeout 0", min_value=0.1,
            max_value=3600.0))
        p("capture_timeout", 10.0, descriptor(
            "Seconds to wait for the driver's capture_burst answer", min_value=0.1,
            max_value=120.0))
        p("presence_threshold", 0.05, descriptor(
            "Finger presence: lit minus dark must exceed this fraction of full scale",
            min_value=0.001, max_value=0.9))
        p("presence_min_coverage", 0.1, descriptor(
            "Finger presence: the bright region must cover this fraction of the image",
            min_value=0.0, max_value=1.0))
        p("presence_period", 0.2, descriptor(
            "Seconds between presence checks while waiting for a finger", min_value=0.0,
            max_value=10.0))
        p("max_motion_px", 2.0, descriptor(
            "A burst whose finger moved more than this (first LED vs its repeat, pixels) "
            "is retaken; ~1/8 of the rig's ridge period (0.5 mm = 16.7 px)",
            min_value=0.0, max_value=100.0))
        p("max_retakes", 5, descriptor(
            "Bursts retaken for motion before the goal is aborted", min_value=0,
            max_value=100, integer=True))
        t = QualityThresholds()
        p("min_coverage", t.min_coverage, descriptor(
            "Verdict: reconstructed finger pixels / image pixels at least", min_value=0.0,
            max_value=1.0))
        p("max_saturated_fraction", t.max_saturated_fraction, descriptor(
            "Verdict: finger pixels saturated in some frame at most", min_value=0.0,
            max_value=1.0))
        p("max_dark_fraction", t.max_dark_fraction, descriptor(
            "Verdict: finger pixels in shadow in some frame at most", min_value=0.0,
            max_value=1.0))
        p("min_ridge_visibility", t.min_ridge_visibility, descriptor(
            "Verdict: ridge-band energy ratio of the normals at least", min_value=0.0,
            max_value=100.0))
        p("max_residual", t.max_residual, descriptor(
            "Verdict: Lambertian fit residual (rms / mean intensity) at most",
            min_value=0.0, max_value=10.0))
        p("recorder", "recorder", descriptor(
            "The recorder node (relative to the namespace) whose bag the result names; "
            "empty = none", read_only=True))

    def _settings(self, goal: Scan.Goal) -> ScanSettings:
        """The goal's settings; raises ``ScanAbortedError`` naming what is impossible."""
        problems = []
        if goal.bursts < 1 or goal.bursts > MAX_BURSTS:
            problems.append(f"bursts {goal.bursts}: must be 1..{MAX_BURSTS}")
        models = [m.value for m in Model]
        if goal.model and goal.model not in models:
            problems.append(f"unknown model {goal.model!r}: use {' or '.join(models)}")
        if not math.isfinite(goal.timeout) or goal.timeout < 0:
            problems.append(f"timeout {goal.timeout}: must be > 0 seconds (0 = the node's "
                            "timeout parameter)")
        values = {name: self.get_parameter(name).value for name in GOAL_PARAMETERS}
        for msg in goal.overrides:
            problem = self._override_problem(msg)
            if problem:
                problems.append(problem)
            else:
                values[msg.name] = Parameter.from_parameter_msg(msg).value
        if goal.model in models:
            values["model"] = goal.model
        if problems:
            raise ScanAbortedError("; ".join(problems))
        options = ReconstructionOptions(
            model=Model(values["model"]), hk_iterations=int(values["hk_iterations"]),
            projection=Projection(values["projection"]),
            mask_threshold=float(values["mask_threshold"]), enhance=bool(values["enhance"]),
            w=int(values["w"]), k=float(values["k"]),
            working_distance_m=float(values["working_distance"]))
        thresholds = QualityThresholds(
            min_coverage=float(values["min_coverage"]),
            max_saturated_fraction=float(values["max_saturated_fraction"]),
            max_dark_fraction=float(values["max_dark_fraction"]),
            min_ridge_visibility=float(values["min_ridge_visibility"]),
            max_motion_px=float(values["max_motion_px"]),
            max_residual=float(values["max_residual"]))
        timeout = goal.timeout or float(self.get_parameter("timeout").value)
        return ScanSettings(
            bursts=int(goal.bursts), timeout_s=timeout, options=options, thresholds=thresholds,
            presence_threshold=float(values["presence_threshold"]),
            presence_min_coverage=float(values["presence_min_coverage"]),
            max_retakes=int(values["max_retakes"]))

    def _override_problem(self, msg: object) -> str | None:
        """Why a goal's parameter override is refused, or None."""
        name = msg.name
        if name not in GOAL_PARAMETERS:
            return (f"override {name!r}: not a parameter a goal can set (one of "
                    f"{', '.join(GOAL_PARAMETERS)})")
        declared = self.get_parameter(name).type_
        try:
            value = Parameter.from_parameter_msg(msg).value
        except (ValueError, TypeError, AttributeError):
            return f"override {name!r}: no value"
        kind = Parameter.Type.from_parameter_value(value) if value is not None else None
        if kind is not declared and not (declared is Parameter.Type.DOUBLE
                                         and kind is Parameter.Type.INTEGER):
            return (f"override {name!r}: a {kind.name.lower() if kind else 'missing'} value, "
                    f"needs {declared.name.lower()}")
        found = self._checks.problems([Parameter(name, value=value)])
        if found:
            return f"override {found[0]}"
        desc = self.describe_parameter(name)
        for r in list(desc.floating_point_range) + list(desc.integer_range):
            if not r.from_value <= value <= r.to_value:
                return f"override {name!r}={value}: outside {r.from_value}..{r.to_value}"
        return None

    # ------------------------------------------------------------------ calibration intake
    def _on_lights(self, msg: LightCalibration) -> None:
        self._lights = msg
        self.get_logger().info(f"light calibration received: {len(msg.directions)} LEDs")

    def _on_flat(self, msg: FlatField) -> None:
        try:
            self._flat_maps = np.stack([image_to_array(m) for m in msg.maps]).astype(
                np.float32)
        except (FingerpsError, ValueError) as exc:
            self.get_logger().error(f"flat field refused: {exc}")

    # ------------------------------------------------------------------ goals
    def _on_goal(self, goal: Scan.Goal) -> GoalResponse:
        reason = None
        try:
            self._settings(goal)
        except ScanAbortedError as exc:
            reason = f"impossible goal: {exc}"
        except FingerpsError as exc:  # a threshold the quality module refuses
            reason = f"impossible goal: {exc}"
        if reason is None and self._lights is None:
            reason = ("no light calibration yet: calibrate the lights (calibrate_lights) or "
                      "start calib_node with a saved calibration")
        if reason is None:
            with self._lock:
                if self._busy:
                    reason = "a scan is already running (one finger at a time); cancel it or " \
                             "wait for its result"
                else:
                    self._busy = True
        if reason is not None:
            self._counts["rejected_goals"] += 1
            self.get_logger().warning(f"Scan goal rejected: {reason}")
            self._pub_rejections.publish(String(data=reason))
            return GoalResponse.REJECT
        self._counts["goals"] += 1
        return GoalResponse.ACCEPT

    def _execute(self, goal_handle: ServerGoalHandle) -> Scan.Result:
        result = Scan.Result()
        try:
            settings = self._settings(goal_handle.request)
            self._scan(goal_handle, settings, result)
        except _CancelledError:
            goal_handle.canceled()
            self._counts["cancelled"] += 1
            result.success = False
            result.message = "cancelled; the LEDs are off"
        except (ScanAbortedError, FingerpsError) as exc:
            goal_handle.abort()
            self._counts["aborted"] += 1
            result.success = False
            result.message = str(exc)
            self.get_logger().warning(f"Scan aborted: {exc}")
        else:
            goal_handle.succeed()
            self._counts["succeeded"] += 1
        finally:
            with self._lock:
                self._busy = False
        return result

    def _scan(self, goal_handle: ServerGoalHandle, settings: ScanSettings,
              result: Scan.Result) -> None:
        deadline = time.monotonic() + settings.timeout_s
        feedback = Scan.Feedback()
        best: _Best | None = None
        done = 0
        state = Scan.Feedback.WAITING_FOR_FINGER
        period = float(self.get_parameter("presence_period").value)
        presence: FingerPresence | None = None

        def report(new_state: int, message: str) -> None:
            feedback.state, feedback.state_name = new_state, STATE_NAMES[new_state]
            feedback.progress = float(done) / settings.bursts
            feedback.bursts_done, feedback.message = done, message
            goal_handle.publish_feedback(feedback)

        while done < settings.bursts:
            if goal_handle.is_cancel_requested:
                raise _CancelledError
            if time.monotonic() > deadline:
                what = ("no finger in view" if state == Scan.Feedback.WAITING_FOR_FINGER
                        else f"only {done} of {settings.bursts} bursts reconstructed")
                raise ScanAbortedError(f"timed out after {settings.timeout_s:g} s: {what} "
                                  f"({result.bursts_captured} bursts captured, "
                                  f"{result.bursts_rejected_motion} retaken for motion)")
            if state == Scan.Feedback.WAITING_FOR_FINGER:
                report(state, "place a finger in view")
                burst = self._capture_burst(publish=False, repeat=False)
                presence = self._presence(burst, settings)
                if presence.present:
                    state = Scan.Feedback.CAPTURING
                else:
                    time.sleep(period)
                continue
            report(Scan.Feedback.CAPTURING, presence.describe() if presence else "")
            burst = self._capture_burst(publish=True, repeat=True)
            result.bursts_captured += 1
            presence = self._presence(burst, settings)
            if not presence.present:
                state = Scan.Feedback.WAITING_FOR_FINGER
                continue
            motion = _motion(burst)
            if motion.magnitude_px > settings.thresholds.max_motion_px:
                result.bursts_rejected_motion += 1
                self._counts["bursts_rejected_motion"] += 1
                self.get_logger().info(
                    f"burst {burst.burst_id} rejected: the finger moved "
                    f"{motion.magnitude_px:.2f} px > {settings.thresholds.max_motion_px:g} px; "
                    "retaking")
                if result.bursts_rejected_motion > settings.max_retakes:
                    raise ScanAbortedError(
                        f"the finger kept moving: {result.bursts_rejected_motion} bursts moved "
                        f"more than {settings.thresholds.max_motion_px:g} px (last "
                        f"{motion.magnitude_px:.2f} px); hold the finger still and try again")
                continue
            report(Scan.Feedback.RECONSTRUCTING, f"burst {burst.burst_id}")
            lights = self._lights
            if lights is None:
                raise ScanAbortedError("no light calibration: calibrate the lights first")
            made = reconstruct_burst(
                burst, lights, self._flat_maps, options=settings.options,
                mono16_full_scale=float(self.get_parameter("mono16_full_scale").value),
                prepared=self._prepared)
            residual = made.result.residual
            figures = quality_figures(
                made.images, mask=made.result.mask, normals_ps=made.result.normals_ps,
                full_scale=made.full_scale, dark=made.dark,
                shadow_fraction=settings.options.shadow_fraction,
                saturation_fraction=settings.options.saturation_fraction,
                motion_px=motion.magnitude_px, motion_correlation=motion.correlation,
                residual=math.nan if residual is None else residual)
            verdict = judge_quality(figures, settings.thresholds)
            done += 1
            candidate = _Best(made, burst, verdict)
            if best is None or candidate.rank() < best.rank():
                best = candidate
        assert best is not None
        report(Scan.Feedback.RECONSTRUCTING, "done")
        self._fill_result(result, best)
        result.session_path = self._session_path()
        self._last_verdict = best.verdict
        self._publish_diagnostics()

    def _fill_result(self, result: Scan.Result, best: _Best) -> None:
        rec, header, verdict = best.made.result, best.burst.header, best.verdict
        f = verdict.figures
        result.success = True
        result.accepted = verdict.accepted
        result.reasons = list(verdict.reasons)
        result.message = (f"burst {best.burst.burst_id}: "
                          + ("accepted" if verdict.accepted
                             else "rejected: " + "; ".join(verdict.reasons)))
        result.normals = array_to_image(ps_to_optical(rec.normals_ps, dtype=np.float32),
                                        encoding="32FC3", header=header)
        shown = rec.enhanced_ps if rec.enhanced_ps is not None else rec.normals_ps
        result.normal_map = array_to_image(normal_map_rgb(shown, mask=rec.mask),
                                           encoding="rgb8", header=header)
        result.points = points_to_cloud(rec.points_optical, rec.point_albedo, header=header)
        try:
            made_print = best.made.fingerprint()
        except RolledPrintError as exc:  # never a garbage print passed as good
            result.accepted = False
            result.reasons = [*result.reasons, f"fingerprint: {exc}"]
            result.message = (f"burst {best.burst.burst_id}: rejected: "
                              + "; ".join(result.reasons))
        else:
            result.fingerprint = array_to_image(
                made_print.image, encoding="mono8",
                header=Header(stamp=header.stamp, frame_id=topics.FINGERPRINT_FRAME))
        result.finger_coverage = f.coverage
        result.saturated_fraction = f.saturated_fraction
        result.dark_fraction = f.dark_fraction
        result.ridge_visibility = f.ridge_visibility
        result.motion_px = f.motion_px
        result.motion_correlation = f.motion_correlation
        result.residual = f.residual
        self.get_logger().info(f"Scan done: {result.message}")

    # ------------------------------------------------------------------ driver, recorder
    def _capture_burst(self, *, publish: bool, repeat: bool) -> Burst:
        timeout = float(self.get_parameter("capture_timeout").value)
        if not self._capture.wait_for_service(timeout_sec=timeout):
            raise ScanAbortedError(f"the driver's {self._capture.srv_name} service is not "
                              f"available after {timeout:g} s: start driver_node")
        request = CaptureBurst.Request(with_dark_frame=True, response_only=not publish,
                                       repeat_first_led=repeat)
        response = self._call(self._capture, request, timeout, "capture_burst")
        if not response.success:
            raise ScanAbortedError(f"burst capture failed: {response.message}")
        return response.burst

    def _call(self, client: Client, request: object, timeout: float, what: str) -> object:
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise ScanAbortedError(f"no answer from {what} within {timeout:g} s")
        return future.result()

    def _session_path(self) -> str:
        """``<bags_dir>/<session_name>`` of the recorder, or "" when it does not answer."""
        client = self._recorder_params
        if client is None or not client.wait_for_service(timeout_sec=0.5):
            return ""
        try:
            response = self._call(client, GetParameters.Request(
                names=["bags_dir", "session_name"]), 2.0, "the recorder")
        except ScanAbortedError:
            return ""
        values = response.values
        if len(values) != 2 or any(v.type != ParameterType.PARAMETER_STRING for v in values):
            return ""
        return f"{values[0].string_value.rstrip('/')}/{values[1].string_value}"

    def _presence(self, burst: Burst, settings: ScanSettings) -> FingerPresence:
        if not burst.frames:
            raise ScanAbortedError("the driver sent a burst without frames")
        lit = image_to_array(burst.frames[0].image)
        dark = image_to_array(burst.dark_frame.image) if burst.has_dark_frame else None
        encoding = burst.frames[0].image.encoding
        full_scale = (float(self.get_parameter("mono16_full_scale").value)
                      if encoding == "mono16" else _FULL_SCALE.get(encoding, 255.0))
        return detect_finger(lit, dark=dark, full_scale=full_scale,
                             threshold=settings.presence_threshold,
                             min_coverage=settings.presence_min_coverage)

    # ------------------------------------------------------------------ diagnostics, exit
    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name=f"{self.get_name()}: verdict")
        verdict = self._last_verdict
        if verdict is None:
            status.level, status.message = DiagnosticStatus.OK, "no scan yet"
            figures = {}
        else:
            status.level = DiagnosticStatus.OK if verdict.accepted else DiagnosticStatus.WARN
            status.message = ("accepted" if verdict.accepted
                              else "rejected: " + "; ".join(verdict.reasons))
            figures = {k: f"{v:.4g}" for k, v in vars(verdict.figures).items()}
        status.values = ([KeyValue(key=k, value=str(v)) for k, v in self._counts.items()]
                         + [KeyValue(key=k, value=v) for k, v in figures.items()]
                         + [KeyValue(key="busy", value=str(self._busy)),
                            KeyValue(key="calibrated", value=str(self._lights is not None))])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(array)

    def destroy_node(self) -> None:
        """Destroy the action server and the node."""
        self._server.destroy()
        super().destroy_node()


class _CancelledError(Exception):
    """The client cancelled the goal."""


def _motion(burst: Burst) -> BurstMotion:
    """Shift between the repeated LED's frame in the burst and its repeat."""
    if not burst.has_repeat_frame:
        raise ScanAbortedError("the driver sent no repeat frame: update driver_node (it needs "
                          "CaptureBurst.repeat_first_led)")
    led = burst.repeat_frame.led_index
    first = next((f for f in burst.frames if f.led_index == led), None)
    if first is None:
        raise ScanAbortedError(f"the burst has no frame of LED {led}, which it repeated")
    return estimate_motion(image_to_array(first.image),
                           image_to_array(burst.repeat_frame.image))


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon scan_node``."""
    return run_node(ScanNode, args=args, name="scan_node", executor=MultiThreadedExecutor,
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
