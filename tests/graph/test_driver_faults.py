"""driver_node against a board_emulator process with faults injected through its control
channel: a burst in which any step failed is never published as complete, the driver
reconnects and reports it, and every burst after a fault is tagged with the LEDs the
emulator actually lit (its switch history, and the simulated camera's images, which it
renders from the emulator's physical state)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from led_history import masks_lit_since
from led_images import led_references, leds_seen
from rclpy.node import Node

from fingerps_driver.board.board_emulator import Fault
from fingerps_driver.board.emulator_control_client import BoardEmulatorControl
from fingerps_msgs.msg import Burst
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import qos, topics

NS = "/" + topics.NAMESPACE
LEDS = list(range(7))
BURST_MASKS = [1 << i for i in LEDS] + [0]  # what a whole burst switches, in order


@pytest.fixture(scope="module")
def references() -> np.ndarray:
    """Each LED's noiseless finger image, centred and normalised: (7, H*W)."""
    return led_references()


def _assert_whole_and_truly_tagged(burst: Burst, references: np.ndarray) -> None:
    assert [f.led_index for f in burst.frames] == LEDS
    assert all(f.burst_id == burst.burst_id and f.led_count == 7 for f in burst.frames)
    seen = leds_seen(burst.frames, references)
    assert seen == LEDS, f"burst {burst.burst_id}: tags {LEDS}, camera saw {seen}"


class _Rig:
    """board_emulator and driver_node processes, and the test's view of them."""

    def __init__(self, ros_node: Node, start_node, spin_until, tmp_path: Path) -> None:
        self.ros_node, self.start_node, self.spin_until = ros_node, start_node, spin_until
        self.link, self.control_path = tmp_path / "board", tmp_path / "control"
        self.control = BoardEmulatorControl(str(self.control_path))
        self.emulator = None
        self.driver = None
        self.bursts: list[Burst] = []
        self.status: dict[str, DiagnosticStatus] = {}
        ros_node.create_subscription(Burst, f"{NS}/{topics.BURST}", self.bursts.append,
                                     qos.BURST_QOS)
        ros_node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, 10)
        self.client = ros_node.create_client(CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}")

    def _on_diag(self, array: DiagnosticArray) -> None:
        for status in array.status:
            self.status[status.name] = status

    def value(self, name: str, key: str) -> str | None:
        status = self.status.get(f"driver: {name}")
        return None if status is None else {kv.key: kv.value for kv in status.values}.get(key)

    def start_emulator(self) -> None:
        self.emulator = self.start_node("fingerps_driver", "board_emulator", "--link",
                                        str(self.link), "--control", str(self.control_path),
                                        "--slow-reply", "0.15")
        self.spin_until(self.control_path.exists, "the emulator's control socket")

    def start_driver(self, *params: str) -> None:
        args = ["--ros-args", "-p", f"port:={self.link}", "-p", "camera:=sim",
                "-p", f"sim.board_control:={self.control_path}",
                "-p", "reconnect_initial_s:=0.1", "-p", "reconnect_max_s:=0.4",
                "-p", "board_timeout:=0.1"]  # a slow_reply (0.15 s) is late; a busy host not
        for param in params:
            args += ["-p", param]
        self.driver = self.start_node("fingerps_driver", "driver_node", *args)
        self.driver.wait_in_graph(self.ros_node, "driver", NS)
        self.spin_until(lambda: self.ros_node.count_publishers(f"{NS}/{topics.BURST}") >= 1,
                        "the driver's burst publisher")
        assert self.client.wait_for_service(timeout_sec=20.0)

    def settle(self, seconds: float) -> None:
        """Spin for ``seconds``, taking in whatever arrives."""
        with pytest.raises(pytest.fail.Exception):
            self.spin_until(lambda: False, "nothing", timeout=seconds)

    def capture(self) -> CaptureBurst.Response:
        future = self.client.call_async(CaptureBurst.Request())
        self.spin_until(future.done, "the capture_burst response", timeout=30.0)
        return future.result()

    def capture_and_check_history(self, references: np.ndarray) -> Burst:
        """A burst that must succeed, with tags matching the emulator's switches."""
        start = time.monotonic()
        response = self.capture()
        assert response.success, response.message
        assert masks_lit_since(self.control.history(100), start) == BURST_MASKS
        _assert_whole_and_truly_tagged(response.burst, references)
        return response.burst

    def close(self) -> None:
        self.control.close()


@pytest.fixture
def rig(ros_node, start_node, spin_until, tmp_path):
    rig = _Rig(ros_node, start_node, spin_until, tmp_path)
    yield rig
    rig.close()


def test_disconnect_mid_burst_fails_it_then_the_driver_reconnects(rig, references) -> None:
    rig.start_emulator()
    rig.start_driver()
    good = rig.capture_and_check_history(references)

    # 7 LEVEL replies, then LED 0's and LED 1's switches; the cable goes at LED 2's
    rig.control.inject(Fault.DISCONNECT, after=9)
    start = time.monotonic()
    failed = rig.capture()
    assert not failed.success
    assert "LED 2" in failed.message and "BoardDisconnectedError" in failed.message
    assert masks_lit_since(rig.control.history(100), start) == [1, 2, 4, 0]
    failed_id = good.burst_id + 1
    rig.spin_until(lambda: rig.value("board", "state") == "disconnected"
                   and rig.status["driver: board"].level == DiagnosticStatus.ERROR
                   and rig.value("bursts", "bursts_failed") == "1",
                   "diagnostics reporting the lost board and the failed burst")
    assert f"burst {failed_id} failed" in rig.value("bursts", "last_error")

    refused = rig.capture()  # while the board is away: at once, saying why
    assert not refused.success and "disconnected" in refused.message
    assert "reconnecting" in refused.message

    rig.settle(0.5)  # a few back-off attempts against the missing port
    rig.control.reconnect()
    rig.spin_until(lambda: rig.value("board", "state") == "connected"
                   and rig.value("board", "reconnects") == "1",
                   "diagnostics reporting the board back")
    assert int(rig.value("board", "disconnects")) == 1
    after = [rig.capture_and_check_history(references) for _ in range(2)]
    assert after[0].burst_id > failed_id

    rig.spin_until(lambda: len(rig.bursts) >= 3, "the published bursts")
    assert failed_id not in [b.burst_id for b in rig.bursts]
    assert all(len(b.frames) == 7 for b in rig.bursts)
    assert "Traceback" not in rig.driver.output


def test_continuous_capture_survives_a_pulled_cable(rig, references) -> None:
    rig.start_emulator()
    rig.start_driver("rate:=10.0")
    rig.spin_until(lambda: len(rig.bursts) >= 2, "continuous bursts", timeout=20.0)
    rig.control.inject(Fault.DISCONNECT, after=20)  # strikes inside the next burst or so
    rig.spin_until(lambda: rig.value("board", "state") == "disconnected",
                   "the driver to notice the lost board")
    failed = int(re.search(r"burst (\d+) failed", rig.value("bursts", "last_error")).group(1))
    published = len(rig.bursts)
    rig.settle(0.6)  # rate 10: five bursts would be due; none is taken without the board
    assert len(rig.bursts) <= published + 1  # at most one already on its way
    assert rig.value("board", "state") == "disconnected"

    rig.control.reconnect()
    rig.spin_until(lambda: len(rig.bursts) >= published + 3, "bursts after the reconnect",
                   timeout=20.0)
    ids = [b.burst_id for b in rig.bursts]
    assert failed not in ids and ids == sorted(ids)
    for burst in rig.bursts:
        _assert_whole_and_truly_tagged(burst, references)
    assert int(rig.value("bursts", "bursts_failed")) == 1


def test_lost_and_garbled_replies_are_retried_within_bounds(rig, references) -> None:
    rig.start_emulator()
    rig.start_driver()  # board_retries 2: three attempts per command, 0.1 s each
    rig.control.inject(Fault.DROP_REPLY, 2, after=8)  # inside the burst: LED 1's switch
    rig.capture_and_check_history(references)

    rig.control.inject(Fault.DROP_REPLY, 3, after=10)  # LED 3's switch never answered
    failed = rig.capture()
    assert not failed.success
    assert "LED 3" in failed.message and "BoardTimeoutError" in failed.message
    rig.capture_and_check_history(references)  # the next one is whole and right

    rig.control.inject(Fault.CORRUPT_BYTE, 1, after=12)
    rig.capture_and_check_history(references)
    rig.control.inject(Fault.CORRUPT_BYTE, 3, after=12)  # LED 5's switch garbled 3 times
    failed = rig.capture()
    assert not failed.success
    assert "LED 5" in failed.message and "BoardProtocolError" in failed.message
    rig.control.inject(Fault.SLOW_REPLY, 1, after=3)  # a late LEVEL reply: resent
    rig.capture_and_check_history(references)

    rig.spin_until(lambda: rig.value("bursts", "bursts_failed") == "2"
                   and rig.value("bursts", "bursts_ok") == "4"
                   and int(rig.value("board", "resends") or 0) >= 2 + 2 + 1 + 2 + 1,
                   "diagnostics counting the failed bursts and the resends")
    assert rig.value("board", "state") == "connected"  # a timeout is not a disconnect


def test_wait_for_port_waits_then_captures_once_the_board_appears(rig, references) -> None:
    rig.start_driver("wait_for_port:=true")
    rig.spin_until(lambda: rig.value("board", "state") == "waiting",
                   "diagnostics saying the driver waits for the board")
    assert rig.status["driver: board"].level == DiagnosticStatus.WARN
    refused = rig.capture()
    assert not refused.success and "is not there yet" in refused.message
    rig.start_emulator()
    rig.spin_until(lambda: rig.value("board", "state") == "connected",
                   "the driver to find the board")
    rig.capture_and_check_history(references)
    assert "waiting for the LED board" in rig.driver.output
