"""The Scan action over DDS: driver_node, calib_node, recorder_node and scan_node as
separate processes on the simulated rig - a finger is scanned within the reconstruction's
accuracy, no finger times out, a finger moving mid-burst is retaken, a cancel leaves the
LEDs off (on a board_emulator process), impossible and concurrent goals are rejected."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from action_msgs.msg import GoalStatus
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.parameter import Parameter
from record_readers import read_ansi_nist, read_iso_19794_2_2005
from std_msgs.msg import String

from fingerps_driver.board.emulator_control_client import BoardEmulatorControl
from fingerps_driver.demo import SPHERE_PLACEMENTS
from fingerps_driver.simulation import RigConfig, SimulatedRig
from fingerps_msgs.action import Scan
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.records.wsq_image import decode_wsq
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array

NS = "/" + topics.NAMESPACE
MAE_LIMIT_DEG = 2.0  # as the demo: HK with calibrated near lights, ~1.3 measured


@pytest.fixture(scope="module")
def calibration_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One calibration for the module: made by the first test, loaded by the others."""
    return tmp_path_factory.mktemp("calibration")


class _Graph:
    """The processes and the test's clients."""

    def __init__(self, ros_node: Node, start_node, spin_until, call_service, set_parameters,
                 tmp_path: Path, calibration_dir: Path) -> None:
        self.node, self.start_node, self.spin_until = ros_node, start_node, spin_until
        self.call = functools.partial(call_service, timeout=60.0)  # (client, request, what)
        self.set_parameters = set_parameters
        self.tmp_path, self.calibration_dir = tmp_path, calibration_dir
        self.scan = ActionClient(ros_node, Scan, f"{NS}/scan")
        self.rejections: list[str] = []
        self.scan_status: dict[str, str] = {}
        ros_node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        ros_node.create_subscription(String, f"{NS}/scan/rejections",
                                     lambda m: self.rejections.append(m.data), 10)

    def _on_diag(self, array: DiagnosticArray) -> None:
        for status in array.status:
            if status.name == "scan: verdict":
                self.scan_status = {kv.key: kv.value for kv in status.values}

    def start(self, *driver_args: str, recorder: bool = False) -> None:
        driver = self.start_node("fingerps_driver", "driver_node", "--ros-args",
                                 *driver_args)
        calib = self.start_node("fingerps_calib", "calib_node", "--ros-args", "-p",
                                f"calibration_dir:={self.calibration_dir}")
        scan = self.start_node("fingerps_recon", "scan_node")
        if recorder:
            rec = self.start_node("fingerps_recon", "recorder_node", "--ros-args", "-p",
                                  f"bags_dir:={self.tmp_path / 'bags'}")
            rec.wait_in_graph(self.node, "recorder", NS)
        driver.wait_in_graph(self.node, "driver", NS)
        calib.wait_in_graph(self.node, "calib", NS)
        scan.wait_in_graph(self.node, "scan", NS)
        assert self.scan.wait_for_server(timeout_sec=20.0)
        self.calibrate()

    def set_param(self, name: str, value: object) -> None:
        (result,) = self.set_parameters("driver", {name: value}, timeout=60.0)
        assert result.successful, result.reason

    def calibrate(self) -> None:
        """Flat field and lights (three sphere placements), unless already saved."""
        if not (self.calibration_dir / "lights.yaml").exists():
            self.set_param("sim.scene", "white_target")
            flat = self.call(self.node.create_client(
                CalibrateFlatField, f"{NS}/calibrate_flat_field"),
                CalibrateFlatField.Request(), "the flat field")
            assert flat.success, flat.message
            self.set_param("sim.scene", "sphere")
            lights_client = self.node.create_client(CalibrateLights,
                                                    f"{NS}/calibrate_lights")
            for i, center in enumerate(SPHERE_PLACEMENTS):
                self.set_param("sim.sphere_center", center)
                lights = self.call(lights_client, CalibrateLights.Request(
                    sphere_radius=0.004, add_placement=i > 0), f"light placement {i}")
                assert lights.success, lights.message
        self.set_param("sim.scene", "finger")
        # the scan node has the (transient-local) calibration: goals are accepted
        self.spin_until(lambda: self.scan_status.get("calibrated") == "True",
                        "the scan node's calibration")

    def send(self, goal: Scan.Goal, feedback: list | None = None):
        """Send a goal; return its handle (accepted or not)."""
        future = self.scan.send_goal_async(
            goal, feedback_callback=(lambda f: feedback.append(f.feedback))
            if feedback is not None else None)
        self.spin_until(future.done, "the goal response", timeout=20.0)
        return future.result()

    def result(self, handle, timeout: float = 120.0):
        future = handle.get_result_async()
        self.spin_until(future.done, "the scan's result", timeout=timeout)
        return future.result()


@pytest.fixture
def graph(ros_node, start_node, spin_until, call_service, set_parameters, tmp_path,
          calibration_dir) -> _Graph:
    return _Graph(ros_node, start_node, spin_until, call_service, set_parameters, tmp_path,
                  calibration_dir)


def test_scan_with_a_finger_meets_the_accuracy_and_bad_goals_are_rejected(graph) -> None:
    graph.start(recorder=True)
    feedback: list[Scan.Feedback] = []
    handle = graph.send(Scan.Goal(bursts=2, model="hk", timeout=90.0), feedback)
    assert handle.accepted
    # one finger at a time: a second goal while the first runs is rejected, with a reason
    second = graph.send(Scan.Goal(bursts=1))
    assert not second.accepted
    graph.spin_until(lambda: any("already running" in r for r in graph.rejections),
                     "the rejection's reason")
    done = graph.result(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.message
    result = done.result
    assert result.success and result.accepted, result.message
    assert list(result.reasons) == []
    assert result.bursts_captured == 2 and result.bursts_rejected_motion == 0
    states = [f.state_name for f in feedback]
    assert {"waiting_for_finger", "capturing", "reconstructing"} <= set(states), states

    rig = SimulatedRig(RigConfig())
    truth = rig.finger_truth()
    normals = optical_to_ps(image_to_array(result.normals))
    found = np.any(normals != 0, axis=2)
    both = truth.mask & found
    assert both.sum() > 0.9 * truth.mask.sum()
    mae = float(np.mean(angular_error_deg(normals, truth.normals_ps)[both]))
    print(f"\nscan: normals mean error {mae:.2f} deg over {both.sum()} px; coverage "
          f"{result.finger_coverage:.3f}, saturated {result.saturated_fraction:.4f}, dark "
          f"{result.dark_fraction:.4f}, ridge visibility {result.ridge_visibility:.4f}, "
          f"motion {result.motion_px:.3f} px (response {result.motion_correlation:.3f}), "
          f"residual {result.residual:.4f}")
    assert 0.0 < mae < MAE_LIMIT_DEG, mae
    assert result.normal_map.encoding == "rgb8" and result.points.width > 50_000
    # the rolled-equivalent print of the best burst, 500 ppi: a fingertip is 10-30 mm
    assert result.fingerprint.encoding == "mono8"
    assert result.fingerprint.header.frame_id == "fingerps_rolled_print_500ppi"
    assert 200 < result.fingerprint.width < 600 and 200 < result.fingerprint.height < 600
    assert 0.4 < result.finger_coverage < 0.7
    assert result.saturated_fraction < 0.02 and result.dark_fraction < 0.25
    assert result.motion_px < 0.5 and 0.0 < result.residual < 0.25
    assert result.ridge_visibility > 0.005
    session = Path(result.session_path)
    assert session.parent == graph.tmp_path / "bags" and session.is_dir()

    # The default finger's ridges are an analytic spiral: NFIQ 2 cannot score its print.
    assert np.isnan(result.nfiq2) and len(result.wsq) == 0  # no records: not asked for

    # A synthetic fingerprint (identity 3), its records asked for, and a print quality
    # threshold above its NFIQ 2: rejected with what to do; NFIQ 2 in the result and on
    # /diagnostics; the records read back from the standards' layouts and NBIS's decoder.
    graph.set_param("sim.finger_identity", 3)
    strict = Parameter("min_nfiq2", value=100.0).to_parameter_msg()
    done = graph.result(graph.send(Scan.Goal(bursts=1, overrides=[strict], records=True)))
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.message
    result = done.result
    assert 0 < result.nfiq2 < 100 and not result.accepted, result.message
    (reason,) = result.reasons
    assert reason.startswith(f"print quality NFIQ 2 {result.nfiq2:.0f} < 100: "), reason
    graph.spin_until(lambda: graph.scan_status.get("nfiq2") == f"{result.nfiq2:.4g}",
                     "NFIQ 2 on /diagnostics")
    print_image = image_to_array(result.fingerprint)
    wsq_image, ppi = decode_wsq(bytes(result.wsq))
    assert ppi == 500 and wsq_image.shape == print_image.shape
    iso = read_iso_19794_2_2005(bytes(result.iso_template))
    assert iso["quality"] == int(result.nfiq2) and len(iso["minutiae"]) > 20
    transaction = read_ansi_nist(bytes(result.ansi_nist_transaction))
    assert [t for t, _ in transaction] == [1, 14, 9]
    assert transaction[1][1][999] == bytes(result.wsq)
    assert list(result.record_problems) == []
    graph.set_param("sim.finger_identity", -1)

    # impossible goals: rejected at once, each with its reason
    bad = [
        (Scan.Goal(bursts=0), "bursts 0"),
        (Scan.Goal(bursts=1, model="phong"), "unknown model 'phong'"),
        (Scan.Goal(bursts=1, timeout=-1.0), "timeout -1.0"),
        (Scan.Goal(bursts=1, overrides=[Parameter("max_motion", value=1.0).to_parameter_msg()]),
         "override 'max_motion'"),
        (Scan.Goal(bursts=1, overrides=[Parameter("max_motion_px",
                                                  value="x").to_parameter_msg()]),
         "override 'max_motion_px'"),
    ]
    for goal, reason in bad:
        before = len(graph.rejections)
        assert not graph.send(goal).accepted, reason
        graph.spin_until(lambda before=before: len(graph.rejections) > before,
                         f"the reason ({reason})")
        assert reason in graph.rejections[-1], graph.rejections[-1]


def test_scan_without_a_finger_times_out_cleanly(graph) -> None:
    graph.start()
    graph.set_param("sim.scene", "empty")
    handle = graph.send(Scan.Goal(bursts=1, timeout=2.0))
    assert handle.accepted
    done = graph.result(handle, timeout=30.0)
    assert done.status == GoalStatus.STATUS_ABORTED
    assert "timed out after 2 s: no finger in view" in done.result.message
    assert not done.result.success and done.result.bursts_captured == 0
    # the node takes the next goal
    graph.set_param("sim.scene", "finger")
    handle = graph.send(Scan.Goal(bursts=1, model="lambert", timeout=60.0))
    assert handle.accepted
    assert graph.result(handle).result.success


def test_a_finger_moving_mid_burst_is_rejected_and_retaken(graph) -> None:
    graph.start()
    # the presence check's burst and the first capture move by 4 px; then the finger stays
    graph.set_param("sim.finger_motion_px", [4.0, 0.0])
    graph.set_param("sim.finger_motion_bursts", 2)
    handle = graph.send(Scan.Goal(bursts=1, model="lambert", timeout=60.0))
    assert handle.accepted
    done = graph.result(handle)
    result = done.result
    assert done.status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert result.bursts_rejected_motion == 1 and result.bursts_captured == 2
    assert result.motion_px < 0.5 and result.accepted, result.message

    # a finger that never stops: retaken up to max_retakes, then aborted saying so
    graph.set_param("sim.finger_motion_bursts", 0)
    handle = graph.send(Scan.Goal(bursts=1, model="lambert", timeout=60.0, overrides=[
        Parameter("max_retakes", value=2).to_parameter_msg()]))
    done = graph.result(handle)
    assert done.status == GoalStatus.STATUS_ABORTED
    assert "kept moving" in done.result.message
    assert done.result.bursts_rejected_motion == 3


def test_cancel_mid_scan_leaves_the_leds_off(graph, start_node, tmp_path) -> None:
    link, control_path = tmp_path / "board", tmp_path / "control"
    start_node("fingerps_driver", "board_emulator", "--link", str(link), "--control",
               str(control_path))
    graph.spin_until(control_path.exists, "the emulator's control socket")
    graph.start("-p", f"port:={link}", "-p", f"sim.board_control:={control_path}")
    control = BoardEmulatorControl(str(control_path))
    try:
        feedback: list[Scan.Feedback] = []
        handle = graph.send(Scan.Goal(bursts=5, model="hk", timeout=90.0), feedback)
        assert handle.accepted
        graph.spin_until(lambda: any(f.state_name == "capturing" for f in feedback),
                         "the scan capturing")
        cancel = handle.cancel_goal_async()
        graph.spin_until(cancel.done, "the cancel response")
        done = graph.result(handle, timeout=30.0)
        assert done.status == GoalStatus.STATUS_CANCELED
        assert control.lit_mask() == 0
        history = control.history(5)
        assert history and history[-1][1] == 0, history
    finally:
        control.close()
