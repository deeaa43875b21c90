"""The driver without ROS: the board's connection, the camera, and the bursts taken with them.

driver_node reads its parameters into settings, makes one ``DriverCore`` and converts what
it returns into messages; it calls the core through ``open``/``start``/``close``,
``capture`` (a request), ``capture_continuous`` (the rate timer), ``set_rate``, ``check_port``
(the diagnostics timer), ``state`` and ``port``, and the simulated rig's setters. A failed
burst says its step as a ``capture.burst.BurstStep`` and its error as the exception's class.
The core opens the hardware (the board first: a missing port is
the first thing to say), sequences each burst through ``capture.burst.capture_burst``
under one lock (no reconnect and no change of the simulated rig in the middle of a burst),
refuses bursts while the board is away, and keeps the counters, timing windows and capture
rate the diagnostics report.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fingerps_driver.board.board_connection import (
    BoardConnection,
    BoardSettings,
    BoardState,
    StartTimer,
)
from fingerps_driver.cameras.camera import Camera
from fingerps_driver.cameras.camera_info_manager import CameraInfoManager
from fingerps_driver.cameras.camera_setup import (
    CameraSettings,
    RigRenderer,
    make_camera,
    open_calibration,
)
from fingerps_driver.capture.burst import BurstResult, BurstStep, capture_burst
from fingerps_driver.capture.burst_plan import BurstPlan
from fingerps_driver.capture.capture_rate import CaptureRate
from fingerps_driver.errors import (
    BoardDisconnectedError,
    BoardRejectedError,
    CameraError,
    FingerpsDriverError,
)
from fingerps_driver.simulation import Scene
from fingerps_ros.log import Log

TIMING_WINDOW = 200
"""Bursts over which the diagnostics' burst and publish time medians/maxima are taken."""


@dataclass
class BurstCounters:
    """What the bursts so far came to (the diagnostics' ``bursts`` and camera status)."""

    ok: int = 0
    failed: int = 0
    last_error: str = ""
    last_burst_failed: bool = False
    last_burst_ms: float = 0.0
    last_publish_ms: float = 0.0
    camera_error: str = ""


def refused(reason: str) -> BurstResult:
    """The result of a burst refused because the board is away."""
    return BurstResult(0, (), None, False, reason, 0.0, failed_step=BurstStep.BOARD,
                       error_type=BoardDisconnectedError)


class DriverCore:
    """The LED board, the camera, and the bursts captured with them.

    Parameters
    ----------
    board : BoardSettings
        The board's parameters.
    camera : CameraSettings
        The camera's parameters.
    log : Log
        The node's logger.
    start_timer : StartTimer
        One-shot timer for the board's reconnect attempts.
    on_board_change : callable
        Called after the board is lost and after it is back.
    """

    def __init__(self, board: BoardSettings, camera: CameraSettings, *, log: Log,
                 start_timer: StartTimer,
                 on_board_change: Callable[[], None] = lambda: None) -> None:
        self.lock = threading.Lock()
        self.camera_settings = camera
        self.board = BoardConnection(board, log=log, lock=self.lock, start_timer=start_timer,
                                     on_change=on_board_change)
        self.camera: Camera | None = None
        self.renderer: RigRenderer | None = None
        self.calibration: CameraInfoManager | None = None
        self.counters = BurstCounters()
        self.burst_ms: deque[float] = deque(maxlen=TIMING_WINDOW)
        self.publish_ms: deque[float] = deque(maxlen=TIMING_WINDOW)
        self.capture_rate = CaptureRate()
        self.burst_id = 0
        self._log = log
        self._closed = False

    def open(self, *, node_name: str, image_topic: str) -> None:
        """Open the board, then the camera and its calibration; all closed again on failure.

        ``node_name`` and ``image_topic`` go into the line saying how to calibrate.

        Raises
        ------
        FingerpsDriverError
            The board or the camera cannot be used; one line saying what to do.
        """
        try:
            missing = self.board.open()  # the board first: a missing port is said first
            camera, self.renderer = make_camera(self.camera_settings, self.board.lit_leds,
                                                emulated=self.board.emulated)
            self.camera = camera
            try:
                camera.open()
            except CameraError as exc:
                raise FingerpsDriverError(f"cannot use the camera: {exc}") from None
            self.calibration = open_calibration(
                self.camera_settings, camera, self.renderer.rig if self.renderer else None,
                node_name=node_name, image_topic=image_topic, log=self._log)
            if camera.refused_settings:
                self._log.warning(
                    f"the camera refused {', '.join(camera.refused_settings)}; it runs with "
                    "its own values there")
            if missing is not None:
                self.board.wait(missing)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ what the node calls
    @property
    def state(self) -> BoardState:
        """The board's connection state."""
        return self.board.state

    @property
    def port(self) -> str:
        """The serial port the board is on (the emulator's pty when emulated)."""
        board = self.board.led_board
        return board.port if board is not None else self.board.settings.port

    def start(self) -> None:
        """Start the board's connection (after :meth:`open` and the node's set-up)."""
        self.board.start()

    def check_port(self) -> bool:
        """The diagnostics timer's check: True if the board's port vanished and the board
        was reported lost now (the loss publishes the diagnostics itself)."""
        return self.board.lose_if_port_vanished()

    def set_rate(self, rate: float) -> None:
        """Continuous capture at ``rate`` bursts/s from now on (0: on request only)."""
        self.capture_rate.set_rate(rate, time.monotonic())

    def capture_continuous(self, plan: BurstPlan, *, with_dark: bool) -> BurstResult | None:
        """The rate timer's burst: None while the board is away (reported in the
        diagnostics; a request would only fail), else :meth:`capture`'s result, counted
        towards the capture rate when whole."""
        if self.board.state is not BoardState.CONNECTED:
            return None
        result = self.capture(plan, with_dark=with_dark)
        if result.ok:
            self.capture_rate.captured(time.monotonic())
        return result

    def capture(self, plan: BurstPlan, *, with_dark: bool,
                repeat_first: bool = False) -> BurstResult:
        """Capture one burst of ``plan``, or refuse it while the board is away.

        A failed burst is counted and logged; a board found closed by it is reported lost.

        Raises
        ------
        FingerpsDriverError
            The driver is closed.
        """
        with self.lock:
            board, camera = self.board.led_board, self.camera
            if self._closed or board is None or camera is None:
                raise FingerpsDriverError("the driver is shutting down")
            if self.board.state is not BoardState.CONNECTED:
                result = refused(self.board.not_connected_reason())
            else:
                self.burst_id += 1
                if self.renderer is not None:
                    self.renderer.start_burst(len(plan.led_order))
                result = capture_burst(
                    board, camera, burst_id=self.burst_id, led_order=plan.led_order,
                    exposures_s=plan.exposures_s, levels=plan.levels, with_dark=with_dark,
                    repeat_first=repeat_first, expected_shape=(camera.height, camera.width))
        if not result.ok:
            self._failed(result)
            return result
        c = self.counters
        c.ok += 1
        c.last_burst_failed = False
        c.last_burst_ms = result.duration_s * 1e3
        self.burst_ms.append(c.last_burst_ms)
        return result

    def published(self, publish_ms: float) -> None:
        """A burst's messages took ``publish_ms`` to build and publish."""
        self.counters.last_publish_ms = publish_ms
        self.publish_ms.append(publish_ms)

    def _failed(self, result: BurstResult) -> None:
        c = self.counters
        c.failed += 1
        c.last_error = result.reason
        c.last_burst_failed = True
        if result.camera_failed:
            c.camera_error = result.reason
        self._log.warning(result.reason, throttle_duration_sec=1.0)
        board = self.board.led_board
        if (board is not None and self.board.state is BoardState.CONNECTED
                and not board.is_open):
            self.board.lost(result.reason)
        elif result.error_type is not None and issubclass(result.error_type,
                                                          BoardRejectedError):
            self._log.error("the board rejected a command: check led_count and "
                            "led_order against the board", throttle_duration_sec=10.0)

    # ------------------------------------------------------------------ the simulated rig
    def show(self, scene: Scene) -> None:
        """The simulated camera shows ``scene`` from the next frame on."""
        if self.renderer is not None:
            self.renderer.scene = scene

    def set_sim_motion(self, motion_px: Sequence[float], motion_bursts: int) -> None:
        """The simulated finger's motion during a burst, counted from now."""
        if self.renderer is not None:
            self.renderer.set_motion(motion_px, motion_bursts)

    def move_sphere(self, center: Sequence[float]) -> None:
        """Move the simulated calibration sphere (between bursts)."""
        if self.renderer is not None:
            with self.lock:  # not in the middle of a burst
                self.renderer.rig = self.renderer.moved_sphere(center)

    def pose_finger(self, finger: Mapping[str, Any]) -> None:
        """Rebuild the simulated finger with ``finger`` (``FingertipShape`` fields) and log
        it."""
        if self.renderer is None:
            return
        rig = self.renderer.posed_finger(finger)  # outside the lock: bursts go on meanwhile
        with self.lock:
            self.renderer.rig = rig
        self._log.info(f"sim finger: {dict(finger)}")

    def close(self) -> None:
        """LEDs off, then close the board, the camera and the emulator (idempotent)."""
        if self._closed:
            return
        self._closed = True
        with self.lock:
            self.board.close()
            if self.camera is not None:
                self.camera.close()
