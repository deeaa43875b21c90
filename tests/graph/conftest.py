"""Fixtures for graph tests: real nodes in subprocesses, talking over DDS on this host only.

- ``ros_domain`` (tests/conftest.py): a ROS domain of the test's own, localhost only.
- ``ros_node``: an rclpy node of the test process in a context of its own (initialised after
  ``ros_domain``, without signal handlers), destroyed at teardown.
- ``start_node(package, executable, *args)``: starts ``install/<pkg>/lib/<pkg>/<exe>`` (built
  by ``make build``) and returns a `NodeProcess`; every process still running at teardown is
  stopped (SIGINT, then SIGKILL of its process group).
- ``wait_for(condition, what, timeout=...)``: polls a condition instead of sleeping blindly.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

REPO = Path(__file__).resolve().parents[2]
INSTALL = REPO / "install"
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 20.0


def wait_until(condition: Callable[[], object], what: str, *, timeout: float = 20.0,
               period: float = 0.05) -> object:
    """Poll ``condition`` until it returns something truthy; fail the test after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(period)


@pytest.fixture
def wait_for() -> Callable[..., object]:
    """``wait_for(condition, what, timeout=20.0)``: poll until truthy, else fail the test."""
    return wait_until


@pytest.fixture
def ros_node(ros_domain: int) -> Iterator[Node]:
    """A node of the test process (``/fingerps_test``) in the test's ROS domain."""
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain,
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("fingerps_test", context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def node_in_graph(graph_node: Node, name: str, namespace: str = "/") -> bool:
    """Whether a node of that name and namespace is visible from ``graph_node``."""
    return (name, namespace) in graph_node.get_node_names_and_namespaces()


class NodeProcess:
    """A node executable running in a subprocess; output goes to ``log_path``."""

    def __init__(self, command: list[str], log_path: Path, env: dict[str, str]) -> None:
        self.command = command
        self.log_path = log_path
        self._log = open(log_path, "wb")  # closed by stop()
        self.process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
            env=env, cwd=REPO, start_new_session=True)

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


def executable(package: str, name: str) -> Path:
    """``install/<package>/lib/<package>/<name>``; fails the test if it is not built."""
    path = INSTALL / package / "lib" / package / name
    if not os.access(path, os.X_OK):
        pytest.fail(f"{path} is not built: run 'make build' (then 'source tools/ros_env.sh')")
    return path


@pytest.fixture
def start_node(ros_domain: int, tmp_path: Path) -> Iterator[Callable[..., NodeProcess]]:
    """``start_node(package, executable, *args)`` -> NodeProcess, stopped at teardown."""
    started: list[NodeProcess] = []

    def start(package: str, name: str, *args: str) -> NodeProcess:
        env = dict(os.environ)
        env.update(PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0",
                   RCUTILS_COLORIZED_OUTPUT="0")
        log_path = tmp_path / f"{name}_{len(started)}.log"
        proc = NodeProcess([str(executable(package, name)), *args], log_path, env)
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
