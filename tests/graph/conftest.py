"""Fixtures for graph tests: real nodes in subprocesses, talking over DDS on this host only.

- ``ros_domain``, ``ros_node`` (tests/conftest.py): a ROS domain of the test's own, localhost
  only, and an rclpy node of the test process in it.
- ``start_node(package, executable, *args)``: starts ``install/<pkg>/lib/<pkg>/<exe>`` (built
  by ``make build``) and returns a `NodeProcess`; every process still running at teardown is
  stopped (SIGINT, then SIGKILL of its process group).
- ``wait_for(condition, what, timeout=...)``: polls a condition instead of sleeping blindly
  (tests/polling.py's ``poll_until``), failing the test on timeout.
- ``spin_until(condition, what, timeout=...)``: spins ``ros_node`` until the condition holds;
  ``call_service(client, request)``: a service's response, spun until it arrives.
- ``set_parameters(node_name, {name: value}, timeout=...)``: one SetParameters request to a
  node of the namespace, each value typed from its Python type; returns the results.
- ``driver_topics``: the test node's subscriptions of the driver's burst and frames topics
  and its capture_burst client.
- ``start_recorder(session, lights=..., flush_period=...)``: a recorder_node recording what
  the test publishes (a light calibration first).
- ``rig_messages``: the LightCalibration and Burst messages of a simulated rig, built in the
  test as calib_node and the driver would publish them.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Vector3
from polling import poll_until
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.client import Client
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_driver.simulation import SimulatedRig
from fingerps_msgs.msg import Burst, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import array_to_image

REPO = Path(__file__).resolve().parents[2]
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 20.0
NS = "/" + topics.NAMESPACE
FRAME_ID = "fingerps_camera_optical_frame"


def wait_until(condition: Callable[[], object], what: str, *, timeout: float = 20.0) -> None:
    """Poll ``condition`` until it returns something truthy; fail the test after ``timeout``."""
    if not poll_until(condition, timeout):
        pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")


@pytest.fixture
def wait_for() -> Callable[..., object]:
    """``wait_for(condition, what, timeout=20.0)``: poll until truthy, else fail the test."""
    return wait_until


def node_in_graph(graph_node: Node, name: str, namespace: str = "/") -> bool:
    """Whether a node of that name and namespace is visible from ``graph_node``."""
    return (name, namespace) in graph_node.get_node_names_and_namespaces()


def _die_with_the_test() -> None:
    """In a started node, before it runs: SIGKILL it if the test process dies (prctl
    PR_SET_PDEATHSIG), so a pytest killed mid-test (a timeout) leaves no graph running."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG


class NodeProcess:
    """A node executable running in a subprocess; output goes to ``log_path``."""

    def __init__(self, command: list[str], log_path: Path, env: dict[str, str]) -> None:
        self.command = command
        self.log_path = log_path
        self._log = open(log_path, "wb")  # closed by stop()
        self.process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
            env=env, cwd=REPO, start_new_session=True, preexec_fn=_die_with_the_test)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def output(self) -> str:
        """Everything the process printed so far (stdout and stderr)."""
        return self.log_path.read_text(errors="replace")

    def running(self) -> bool:
        return self.process.poll() is None

    def wait_in_graph(self, graph_node: Node, name: str, namespace: str = "/", *,
                      timeout: float = START_TIMEOUT_S) -> None:
        """Wait until the node appears in the graph; fail early if the process dies."""
        def ready() -> bool:
            if not self.running():
                pytest.fail(f"{self.command[0]} exited with {self.process.returncode} before "
                            f"{namespace.rstrip('/')}/{name} appeared:\n{self.output}")
            return node_in_graph(graph_node, name, namespace)
        wait_until(ready, f"node {namespace.rstrip('/')}/{name} in the graph", timeout=timeout)

    def send_signal(self, signum: int) -> None:
        """Send a signal to the node's process (as Ctrl-C or ``kill`` would)."""
        self.process.send_signal(signum)

    def signal_until_exit(self, timeout: float) -> int:
        """SIGINT, then SIGTERM and SIGINT in turn every 10 ms until the process has exited or
        ``timeout`` s have passed (a second Ctrl-C, the process group's SIGINT, a supervisor's
        SIGTERM); returns how many signals were sent."""
        self.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        sent = 1
        while self.running() and time.monotonic() < deadline:
            self.send_signal(signal.SIGTERM if sent % 2 else signal.SIGINT)
            sent += 1
            time.sleep(0.01)
        return sent

    def wait(self, timeout: float = STOP_TIMEOUT_S) -> int:
        """Wait for the process to exit and return its exit code; fail on timeout."""
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{self.command[0]} still running {timeout:.0f} s later:\n{self.output}")

    def stop(self) -> None:
        """End the process if it still runs (SIGINT, then SIGKILL of its process group)."""
        try:
            if self.running():
                self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    pass
            try:
                os.killpg(self.process.pid, signal.SIGKILL)  # and anything it started
            except (ProcessLookupError, PermissionError):
                pass
            self.process.wait(timeout=STOP_TIMEOUT_S)
        finally:
            self._log.close()


@pytest.fixture
def start_node(ros_domain: int, tmp_path: Path,
               installed: Callable[[str, str], Path]) -> Iterator[Callable[..., NodeProcess]]:
    """``start_node(package, executable, *args)`` -> NodeProcess, stopped at teardown."""
    started: list[NodeProcess] = []

    def start(package: str, name: str, *args: str) -> NodeProcess:
        env = dict(os.environ)
        env.update(PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0",
                   RCUTILS_COLORIZED_OUTPUT="0")
        log_path = tmp_path / f"{name}_{len(started)}.log"
        proc = NodeProcess([str(installed(package, name)), *args], log_path, env)
        started.append(proc)
        return proc

    try:
        yield start
    finally:
        for proc in reversed(started):
            proc.stop()


@pytest.fixture
def spin_until(ros_node: Node) -> Iterator[Callable[..., None]]:
    """``spin_until(condition, what, timeout=20.0)``: spin ``ros_node`` until truthy."""
    executor = SingleThreadedExecutor(context=ros_node.context)
    executor.add_node(ros_node)

    def until(condition: Callable[[], object], what: str, *, timeout: float = 20.0) -> None:
        def step() -> object:
            executor.spin_once(timeout_sec=0.05)
            return condition()
        wait_until(step, what, timeout=timeout)

    try:
        yield until
    finally:
        executor.remove_node(ros_node)
        executor.shutdown()


@pytest.fixture
def call_service(spin_until: Callable[..., None]) -> Callable[..., object]:
    """``call_service(client, request, what=None, timeout=30.0)``: the service's response,
    ``ros_node`` spun until it arrives; fails the test if the service is not there."""
    def call(client: Client, request: object, what: str | None = None, *,
             timeout: float = 30.0) -> object:
        assert client.wait_for_service(timeout_sec=20.0), f"{client.srv_name} not available"
        future = client.call_async(request)
        spin_until(future.done, what or f"the response of {client.srv_name}", timeout=timeout)
        return future.result()
    return call


@pytest.fixture
def set_parameters(ros_node: Node,
                   call_service: Callable[..., object]) -> Callable[..., list[SetParametersResult]]:
    """``set_parameters(node_name, values, timeout=30.0)``: sets ``values`` ({name: value})
    on the node ``/fingerps/<node_name>`` in one SetParameters request, ``ros_node`` spun
    until the response arrives; each value is typed from its Python type by
    ``rclpy.parameter.Parameter`` (bool, int, float, str, or a list or tuple of one of them).
    Returns the node's results (``successful``, ``reason``), one per value in order; the test
    asserts on them."""
    clients: dict[str, Client] = {}

    def set_values(node_name: str, values: dict[str, object], *,
                   timeout: float = 30.0) -> list[SetParametersResult]:
        if node_name not in clients:
            clients[node_name] = ros_node.create_client(
                SetParameters, f"{NS}/{node_name}/set_parameters")
        request = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        response = call_service(clients[node_name], request,
                                f"setting {', '.join(values)} on {node_name}", timeout=timeout)
        assert len(response.results) == len(values), response.results
        return list(response.results)
    return set_values


class DriverTopics(NamedTuple):
    """What the test node hears of a driver: its bursts and tagged frames as they arrive."""

    bursts: list[Burst]
    frames: list[TaggedFrame]
    capture: Client  # of the capture_burst service


@pytest.fixture
def driver_topics(ros_node: Node) -> DriverTopics:
    """The test node subscribed to the driver's burst and frames topics (their QoS), with a
    capture_burst client."""
    topics_heard = DriverTopics([], [], ros_node.create_client(
        CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}"))
    ros_node.create_subscription(Burst, f"{NS}/{topics.BURST}", topics_heard.bursts.append,
                                 qos.BURST_QOS)
    ros_node.create_subscription(TaggedFrame, f"{NS}/{topics.FRAMES}",
                                 topics_heard.frames.append, qos.SENSOR_QOS)
    return topics_heard


class Recording(NamedTuple):
    """A recorder_node process, the test's burst publisher and the recorder's bags_dir."""

    recorder: NodeProcess
    burst_pub: Publisher
    bags: Path


@pytest.fixture
def start_recorder(ros_node: Node, start_node: Callable[..., NodeProcess],
                   tmp_path: Path) -> Callable[..., Recording]:
    """``start_recorder(session, lights=..., flush_period=...)``: publishes ``lights`` (the
    calibration, before the recorder exists: transient-local brings it), starts recorder_node
    (bags_dir ``tmp_path / "bags"``, that session name, ``record_outputs:=false``) and waits
    until it subscribes to the test's burst publisher."""
    def start(session: str, *, lights: LightCalibration, flush_period: float) -> Recording:
        lights_pub = ros_node.create_publisher(
            LightCalibration, f"{NS}/{topics.LIGHT_CALIBRATION}", qos.CALIBRATION_QOS)
        lights_pub.publish(lights)
        burst_pub = ros_node.create_publisher(Burst, f"{NS}/{topics.BURST}", qos.BURST_QOS)
        bags = tmp_path / "bags"
        recorder = start_node(
            "fingerps_recon", "recorder_node", "--ros-args",
            "-p", f"bags_dir:={bags}", "-p", f"session_name:={session}",
            "-p", "record_outputs:=false", "-p", f"flush_period:={flush_period}")
        recorder.wait_in_graph(ros_node, "recorder", NS)
        wait_until(lambda: burst_pub.get_subscription_count() >= 1,
                   "the recorder's burst subscription")
        return Recording(recorder, burst_pub, bags)
    return start


class RigMessages:
    """A simulated rig's messages as calib_node and the driver publish them (frame
    ``FRAME_ID``), built in the test."""

    def __init__(self, rig: SimulatedRig) -> None:
        self.rig = rig

    def light_calibration(self, camera_name: str) -> LightCalibration:
        """The rig's true distant lights from the apex (optical frame) and relative
        intensities at the apex (scaled to a maximum of 1)."""
        directions = ps_to_optical(self.rig.light_directions_ps())
        intensities = self.rig.light_intensities()
        return LightCalibration(
            header=Header(frame_id=FRAME_ID), camera_name=camera_name,
            directions=[Vector3(x=float(x), y=float(y), z=float(z)) for x, y, z in directions],
            relative_intensities=[float(i) for i in intensities / intensities.max()],
            sphere_radius=self.rig.config.sphere.radius_m)

    def burst(self, images: np.ndarray, burst_id: int, *, leds: list[int] | None = None,
              encoding: str = "mono8", nanosec: int | None = None) -> Burst:
        """A burst of ``images`` (one per LED; only ``leds`` if given) stamped
        ``1000 + burst_id`` s and ``nanosec`` ns (``burst_id`` if None)."""
        header = Header(stamp=Time(sec=1000 + burst_id,
                                   nanosec=burst_id if nanosec is None else nanosec),
                        frame_id=FRAME_ID)
        count = len(images)
        frames = [TaggedFrame(header=header, burst_id=burst_id, led_index=k, led_count=count,
                              exposure_time=0.01, led_intensity=1.0,
                              image=array_to_image(images[k], encoding=encoding, header=header))
                  for k in (range(count) if leds is None else leds)]
        info = CameraInfo(header=header, width=self.rig.camera.width,
                          height=self.rig.camera.height,
                          k=[float(x) for x in self.rig.camera_matrix.reshape(-1)])
        return Burst(header=header, burst_id=burst_id, frames=frames, camera_info=info)


@pytest.fixture(scope="module")
def rig_messages(rig: SimulatedRig) -> RigMessages:
    """The LightCalibration and Burst messages of the module's ``rig``."""
    return RigMessages(rig)
