"""calib_node answers every bad request and bad parameter instead of dying.

A real calib_node process (no driver: the frames are in the requests, rendered here by the
simulated rig; the intrinsics come from a camera_info this test publishes). Each bad call
gets ``success: false`` and a reason naming the input and what to do; the node keeps
running, the calibration in force stays as it was, the next good call succeeds, no
traceback is printed, and ``/diagnostics`` counts the calls. The bad inputs include
sphere radii 1e-300, -1, inf and 1e300, 0x0, 1x1 and 4x4 flat-field frames, and the
parameters reference_point [0, 0, inf] and camera_name ''.
"""

from __future__ import annotations

import math
import signal

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_msgs.msg import FlatField, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import array_to_image

NS = "/" + topics.NAMESPACE
LIGHTS_TOPIC = f"{NS}/{topics.LIGHT_CALIBRATION}"
FLAT_TOPIC = f"{NS}/{topics.FLAT_FIELD}"
DIAGNOSTIC_NAME = "calib: calibration"


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig())


def _frames(images: np.ndarray) -> list[TaggedFrame]:
    n_led = len(images)
    return [TaggedFrame(burst_id=1, led_index=k, led_count=n_led,
                        image=array_to_image(np.ascontiguousarray(im), encoding="mono8"))
            for k, im in enumerate(images)]


def _render(rig: SimulatedRig, scene: Scene) -> list[TaggedFrame]:
    return _frames(rig.render_burst(scene, seed=0))


def _blank(rig: SimulatedRig, size: int) -> list[TaggedFrame]:
    return _frames(np.full((rig.led_count, size, size), 120, np.uint8))


def _camera_info(rig: SimulatedRig) -> CameraInfo:
    info = CameraInfo(width=rig.camera.width, height=rig.camera.height,
                      distortion_model="plumb_bob", d=[0.0] * 5)
    info.header.frame_id = "fingerps_camera_optical_frame"
    info.k = [float(x) for x in np.asarray(rig.camera_matrix).ravel()]
    return info


def _latest(received: list, spin_until, what: str):
    spin_until(lambda: received, what)
    return received[-1]


def _start_calib(ros_node: Node, start_node, *args: str):
    calib = start_node("fingerps_calib", "calib_node", *args)
    calib.wait_in_graph(ros_node, "calib", NS)
    return calib


def _assert_refused(response, calib, *words: str) -> None:
    assert not response.success, response.message
    message = response.message.lower()
    assert all(word.lower() in message for word in words), response.message
    assert calib.running(), calib.output


class _Graph:
    """The test's clients and subscriptions of calib_node's services and topics."""

    def __init__(self, ros_node: Node, rig: SimulatedRig, call_service) -> None:
        self.node, self.rig, self.call_service = ros_node, rig, call_service
        self.flat_client = ros_node.create_client(CalibrateFlatField,
                                                  f"{NS}/{topics.CALIBRATE_FLAT_FIELD}")
        self.lights_client = ros_node.create_client(CalibrateLights,
                                                    f"{NS}/{topics.CALIBRATE_LIGHTS}")
        self.flats: list[FlatField] = []
        self.lights: list[LightCalibration] = []
        self.statuses: list[DiagnosticStatus] = []
        self.refused_while_waiting = 0
        ros_node.create_subscription(FlatField, FLAT_TOPIC, self.flats.append,
                                     qos.CALIBRATION_QOS)
        ros_node.create_subscription(LightCalibration, LIGHTS_TOPIC, self.lights.append,
                                     qos.CALIBRATION_QOS)
        ros_node.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS,
            lambda msg: self.statuses.extend(
                s for s in msg.status if s.name == DIAGNOSTIC_NAME), 10)

    def flat(self, frames: list[TaggedFrame]):
        return self.call_service(self.flat_client, CalibrateFlatField.Request(frames=frames),
                                 timeout=60.0)

    def lights_call(self, radius: float, frames: list[TaggedFrame]):
        return self.call_service(
            self.lights_client, CalibrateLights.Request(sphere_radius=radius, frames=frames),
            timeout=60.0)

    def publish_camera_info(self, spin_until, frames: list[TaggedFrame]):
        """Publish the rig's camera_info (10 Hz) until calib_node has it; returns the light
        calibration made while waiting (the default sphere_radius is the rig's)."""
        publisher = self.node.create_publisher(CameraInfo, f"{NS}/{topics.CAMERA_INFO}",
                                               qos.SENSOR_QOS)
        self.node.create_timer(0.1, lambda: publisher.publish(_camera_info(self.rig)))
        answers = []

        def received() -> bool:
            answers.append(self.lights_call(0.0, frames))
            return not answers[-1].message.startswith("no camera intrinsics")
        spin_until(received, "calib_node to receive the camera_info", timeout=30.0)
        self.refused_while_waiting = len(answers) - 1
        return answers[-1]

    def values(self) -> dict[str, str]:
        return {kv.key: kv.value for kv in self.statuses[-1].values} if self.statuses else {}


def _stopped_cleanly(calib) -> None:
    calib.send_signal(signal.SIGINT)
    assert calib.wait() == 0, calib.output
    assert "Traceback" not in calib.output, calib.output


def test_bad_flat_field_frames_are_refused_and_the_node_keeps_serving(
        ros_node: Node, start_node, spin_until, call_service, rig) -> None:
    calib = _start_calib(ros_node, start_node)
    graph = _Graph(ros_node, rig, call_service)
    white = _render(rig, Scene.WHITE_TARGET)

    # Before calib_node has seen a camera_info (its image size is unknown).
    good = graph.flat(white)
    assert good.success, good.message
    for size in (0, 1, 4):
        refused = graph.flat(_blank(rig, size))
        _assert_refused(refused, calib, f"{size}x{size}", "64x64")
    assert _latest(graph.flats, spin_until, "the flat field in force") == good.flat_field

    # Once the camera's size is known, frames of another size are refused.
    first_lights = graph.publish_camera_info(spin_until, _render(rig, Scene.SPHERE))
    assert first_lights.success, first_lights.message
    wrong_size = graph.flat(_blank(rig, 64))
    _assert_refused(wrong_size, calib, "64x64", f"{rig.camera.width}x{rig.camera.height}")
    assert graph.flats[-1] == good.flat_field
    refused = str(4 + graph.refused_while_waiting)
    spin_until(lambda: graph.values().get("calls_refused") == refused,
               f"/diagnostics counting {refused} refused calls")
    assert graph.statuses[-1].level == DiagnosticStatus.WARN, graph.statuses[-1]
    assert "64x64" in graph.values()["last_error"]

    again = graph.flat(white)  # the next good call
    assert again.success, again.message
    spin_until(lambda: graph.statuses[-1].level == DiagnosticStatus.OK,
               "/diagnostics back to OK")
    assert graph.values()["calls_ok"] == "3", graph.values()  # flat, lights, flat
    _stopped_cleanly(calib)


@pytest.mark.parametrize("radius", [1e-300, -1.0, math.inf, 1e300, math.nan, 1.0])
def test_a_bad_sphere_radius_is_refused_and_the_node_keeps_serving(
        ros_node: Node, start_node, spin_until, call_service, rig, radius: float) -> None:
    calib = _start_calib(ros_node, start_node)
    graph = _Graph(ros_node, rig, call_service)
    sphere = _render(rig, Scene.SPHERE)
    good = graph.publish_camera_info(spin_until, sphere)
    assert good.success, good.message
    in_force = _latest(graph.lights, spin_until, "the light calibration in force")
    assert in_force == good.calibration

    refused = graph.lights_call(radius, sphere)
    _assert_refused(refused, calib, "sphere_radius", "between 0.0005 and 0.05 m",
                    "stays in force")
    spin_until(lambda: graph.statuses and graph.statuses[-1].level == DiagnosticStatus.WARN,
               "/diagnostics WARN after the refused call")
    values = graph.values()
    assert int(values["calls_refused"]) >= 1 and values["calls_ok"] == "1", values
    assert values["calls_failed_unexpectedly"] == "0", values
    assert "sphere_radius" in values["last_error"], values
    assert graph.lights[-1] == good.calibration  # nothing new published

    again = graph.lights_call(rig.config.sphere.radius_m, sphere)
    assert again.success, again.message
    _stopped_cleanly(calib)


def test_an_unexpected_error_in_a_callback_is_answered_logged_and_counted(
        ros_domain: int) -> None:
    """In process: a handler that raises what nobody expected (a bug) still answers."""
    import rclpy

    from fingerps_calib.calib_node import CalibNode

    rclpy.init(domain_id=ros_domain, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = CalibNode()

        def broken(request, response):
            raise ZeroDivisionError("float division by zero\nsecond line")
        callback = node._answering("calibrate_lights", broken)
        answer = callback(CalibrateLights.Request(), CalibrateLights.Response())
        assert not answer.success
        assert "ZeroDivisionError: float division by zero second line" in answer.message
        assert "\n" not in answer.message
        counts = node._calls.snapshot()
        assert counts["unexpected"] == 1 and counts["last_unexpected"], counts
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_bad_parameters_are_refused_with_a_reason(
        ros_node: Node, start_node, call_service, set_parameters) -> None:
    calib = _start_calib(ros_node, start_node)
    getter = ros_node.create_client(GetParameters, f"{NS}/calib/get_parameters")
    names = ["reference_point", "camera_name", "sphere_radius"]
    before = call_service(getter, GetParameters.Request(names=names), timeout=60.0).values

    bad = [
        ("reference_point", [0.0, 0.0, math.inf], "finite"),
        ("reference_point", [math.nan, 0.0, 0.09], "finite"),
        ("reference_point", [0.0, 0.0, -0.09], "z > 0"),
        ("camera_name", "", "not be empty"),
        ("camera_name", "  ", "not be empty"),
    ]
    for radius in (math.inf, math.nan, 1e-300, 1.0):
        bad.append(("sphere_radius", radius, "sphere_radius"))
    for name, value, reason in bad:
        (result,) = set_parameters("calib", {name: value}, timeout=60.0)
        assert not result.successful, (name, value)
        assert reason in result.reason, result.reason
    after = call_service(getter, GetParameters.Request(names=names), timeout=60.0).values
    assert after == before

    (good,) = set_parameters("calib", {"camera_name": "rig_2"}, timeout=60.0)
    assert good.successful, good.reason
    assert calib.running(), calib.output
    assert "Traceback" not in calib.output, calib.output


@pytest.mark.parametrize("override", [
    "reference_point:=[0.0, 0.0, .inf]",
    "reference_point:=[.nan, 0.0, 0.09]",
    "camera_name:=''",
])
def test_a_bad_parameter_on_the_command_line_stops_the_node_with_one_line(
        start_node, override: str) -> None:
    calib = start_node("fingerps_calib", "calib_node", "--ros-args", "-p", override)
    assert calib.wait() == 2, calib.output
    lines = calib.output.strip().splitlines()
    name = override.split(":=")[0]
    assert len(lines) == 1 and lines[0].startswith(f"[calib_node] error: {name}="), lines
    assert "Traceback" not in calib.output
