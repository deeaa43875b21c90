"""scan_node: the Scan action - wait for a finger, capture still bursts, reconstruct, judge.

Thin ROS adapter around `scan.scan_sequence.ScanSequence` (the goal's states as feedback,
its verdict, timeout and cancel). One goal at a time: a goal arriving while another runs, or
one with impossible values, is rejected at once, the reason logged and published on
``scan/rejections`` (ROS 2's goal response carries no text). It calls the driver's
``capture_burst`` (``response_only`` while waiting for a finger; ``repeat_first_led`` and
published, so recorded, while capturing), reconstructs with the calibration in force
(``reconstruction.calibration_in_force``, each message checked as recon_node checks it) and
publishes the result, the feedback and the verdict on ``/diagnostics``.
"""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String

from fingerps_msgs.action import Scan
from fingerps_msgs.msg import FlatField, LightCalibration
from fingerps_msgs.srv import CaptureBurst
from fingerps_recon.errors import FingerpsReconError, ScanAbortedError
from fingerps_recon.photometric.pipeline import ReconstructionOptions
from fingerps_recon.reconstruction.burst_intake import BurstLimits, scan_burst
from fingerps_recon.reconstruction.burst_reconstruction import (
    BurstReconstruction,
    reconstruct_burst,
)
from fingerps_recon.reconstruction.calibration_in_force import CalibrationInForce
from fingerps_recon.reconstruction.outputs import fill_scan_result
from fingerps_recon.scan.scan_sequence import (
    GoalEnd,
    ScanBurst,
    ScanOutcome,
    ScanSequence,
)
from fingerps_recon.scan.scan_settings import (
    GOAL_PARAMETERS,
    SCAN_PARAMETERS,
    ScanSettings,
    goal_settings,
)
from fingerps_ros import qos, topics
from fingerps_ros.diagnostics import PERIOD_S, DiagnosticsPublisher, key_values
from fingerps_ros.errors import FingerpsError
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import declare_parameters
from fingerps_ros.service_call import call_service

SCAN = "scan"                       # fingerps_msgs/action/Scan
SCAN_REJECTIONS = "scan/rejections"  # std_msgs/String: why a goal was rejected
_LIMITS = BurstLimits()  # a burst's and a flat field's image bounds: recon_node's defaults


class ScanNode(Node):
    """Serves the Scan action over the driver's capture_burst service."""

    def __init__(self, **node_options: object) -> None:
        """``node_options``: rclpy ``Node`` keywords (a test gives its ``context``)."""
        super().__init__("scan", namespace=topics.NAMESPACE, **node_options)
        self._checks = declare_parameters(self, SCAN_PARAMETERS)
        self._checks.refuse_unknown_overrides(self)
        self._group = ReentrantCallbackGroup()
        self._calibration = CalibrationInForce()
        self._sequence = ScanSequence(capture=self._capture_burst, reconstruct=self._reconstruct,
                                      logger=self.get_logger())
        self.create_subscription(LightCalibration, topics.LIGHT_CALIBRATION, self._on_lights,
                                 qos.CALIBRATION_QOS, callback_group=self._group)
        self.create_subscription(FlatField, topics.FLAT_FIELD, self._on_flat,
                                 qos.CALIBRATION_QOS, callback_group=self._group)
        self._capture = self.create_client(CaptureBurst, topics.CAPTURE_BURST,
                                           callback_group=self._group)
        recorder = str(self._value("recorder"))
        self._recorder_params = (self.create_client(
            GetParameters, f"{recorder}/get_parameters", callback_group=self._group)
            if recorder else None)
        self._pub_rejections = self.create_publisher(String, SCAN_REJECTIONS, 10)
        self._diagnostics = DiagnosticsPublisher(self, self._statuses)
        self.create_timer(PERIOD_S, self._diagnostics.publish, callback_group=self._group)
        self._server = ActionServer(
            self, Scan, SCAN, execute_callback=self._execute, goal_callback=self._on_goal,
            cancel_callback=lambda _goal: CancelResponse.ACCEPT, callback_group=self._group)
        self.get_logger().info("scan ready: waiting for a light calibration and goals")

    def _value(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _settings(self, goal: Scan.Goal) -> ScanSettings:
        """The goal's settings; raises ``ImpossibleGoalError`` naming what is impossible."""
        values = {name: self._value(name) for name in GOAL_PARAMETERS}
        problems = []
        for msg in goal.overrides:
            problem = self._override_problem(msg)
            if problem:
                problems.append(problem)
            else:
                values[msg.name] = Parameter.from_parameter_msg(msg).value
        return goal_settings(bursts=goal.bursts, model=goal.model, timeout_s=goal.timeout,
                             values=values, problems=problems,
                             default_timeout_s=float(self._value("timeout")),
                             presence_period_s=float(self._value("presence_period")),
                             records=goal.records)

    def _override_problem(self, msg: Any) -> str | None:
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

    def _on_lights(self, msg: LightCalibration) -> None:
        try:
            self._calibration.offer_lights(msg)
        except FingerpsError as exc:
            self.get_logger().error(f"light calibration refused: {exc}")
            return
        self.get_logger().info(f"light calibration received: {len(msg.directions)} LEDs")

    def _on_flat(self, msg: FlatField) -> None:
        try:
            self._calibration.offer_flat(msg, _LIMITS)
        except FingerpsError as exc:
            self.get_logger().error(f"flat field refused: {exc}")

    def _on_goal(self, goal: Scan.Goal) -> GoalResponse:
        problem = None
        try:
            self._settings(goal)
        except FingerpsError as exc:  # a threshold the quality module refuses among them
            problem = f"impossible goal: {exc}"
        reason = self._sequence.admit(problem,
                                      calibrated=self._calibration.lights is not None)
        if reason is not None:
            self.get_logger().warning(f"Scan goal rejected: {reason}")
            self._pub_rejections.publish(String(data=reason))
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _execute(self, goal_handle: ServerGoalHandle) -> Scan.Result:
        result = Scan.Result()
        end = self._sequence.execute(
            lambda: self._settings(goal_handle.request),
            report=lambda s: goal_handle.publish_feedback(Scan.Feedback(
                state=int(s.state), state_name=s.state.name.lower(), progress=s.progress,
                bursts_done=s.bursts_done, message=s.message)),
            deliver=lambda outcome: self._deliver(result, outcome),
            cancelled=lambda: goal_handle.is_cancel_requested)
        {GoalEnd.SUCCEEDED: goal_handle.succeed, GoalEnd.ABORTED: goal_handle.abort,
         GoalEnd.CANCELLED: goal_handle.canceled}[end.end]()
        result.bursts_captured = end.tally.bursts_captured
        result.bursts_rejected_motion = end.tally.bursts_rejected_motion
        if end.end is not GoalEnd.SUCCEEDED:
            result.success, result.message = False, end.message
        return result

    def _deliver(self, result: Scan.Result, outcome: ScanOutcome) -> None:
        """Fill the result of a scan that succeeded, then publish its verdict."""
        fill_scan_result(result, outcome)
        result.session_path = self._session_path()
        self._diagnostics.publish()

    def _capture_burst(self, publish: bool, repeat: bool) -> ScanBurst:
        timeout = float(self._value("capture_timeout"))
        if not self._capture.wait_for_service(timeout_sec=timeout):
            raise ScanAbortedError(f"the driver's {self._capture.srv_name} service is not "
                                   f"available after {timeout:g} s: start driver_node")
        request = CaptureBurst.Request(with_dark_frame=True, response_only=not publish,
                                       repeat_first_led=repeat)
        response = self._call(self._capture, request, timeout, "capture_burst")
        if not response.success:
            raise ScanAbortedError(f"burst capture failed: {response.message}")
        return scan_burst(response.burst,
                          mono16_full_scale=float(self._value("mono16_full_scale")))

    def _reconstruct(self, burst: ScanBurst, options: ReconstructionOptions
                     ) -> BurstReconstruction:
        return reconstruct_burst(
            burst.source, self._calibration, options=options,
            mono16_full_scale=float(self._value("mono16_full_scale")), limits=_LIMITS)

    def _call(self, client: Client, request: object, timeout: float, what: str) -> Any:
        response = call_service(client, request, timeout)
        if response is None:
            raise ScanAbortedError(f"no answer from {what} within {timeout:g} s")
        return response

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

    def _statuses(self) -> list[DiagnosticStatus]:
        state = self._sequence.status(calibrated=self._calibration.lights is not None)
        return [DiagnosticStatus(
            name=f"{self.get_name()}: verdict", message=state.message,
            level=DiagnosticStatus.OK if state.ok else DiagnosticStatus.WARN,
            values=key_values(state.values))]

    def destroy_node(self) -> None:
        """Destroy the action server and the node."""
        self._server.destroy()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon scan_node``."""
    return run_node(ScanNode, args=args, name="scan_node", executor=MultiThreadedExecutor,
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
