"""The benchmark's own rclpy node beside a process it measures: a context of its own in the
benchmark's ROS domain (no signal handlers), and spinning until a condition holds while that
process still runs."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # polling
from polling import poll_until

if TYPE_CHECKING:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node


class BenchNode:
    """The benchmark's node and its executor, watching one other process."""

    def __init__(self, node: Node, executor: SingleThreadedExecutor,
                 watched: subprocess.Popen, watched_name: str, period: float) -> None:
        self.node, self.executor = node, executor
        self.watched, self.watched_name, self.period = watched, watched_name, period

    def spin_until(self, condition: Callable[[], object], what: str, timeout: float) -> None:
        """Spin (``period`` s at a time) until ``condition()`` is truthy; RuntimeError if the
        watched process exits or ``timeout`` s pass first."""
        def step() -> object:
            if self.watched.poll() is not None:
                raise RuntimeError(f"{self.watched_name} exited with {self.watched.returncode}")
            self.executor.spin_once(timeout_sec=self.period)
            return condition()

        if not condition() and not poll_until(step, timeout, interval_s=0.0):
            raise RuntimeError(f"timed out waiting for {what}")


@contextmanager
def bench_node(name: str, domain: int, *, watched: subprocess.Popen, watched_name: str,
               period: float, namespace: str | None = None) -> Iterator[BenchNode]:
    """A node ``name`` in a context of its own in ROS domain ``domain``, destroyed (and the
    context shut down) when the block ends."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=domain,
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, namespace=namespace, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield BenchNode(node, executor, watched, watched_name, period)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
