"""The LED board over the driver's life: opened and checked at start, lost, reopened.

No ROS here: ``driver_core.DriverCore`` owns one, the node gives it a one-shot timer. A
disconnect (a burst fails with the port closed, or the port vanishes) closes the port,
reports it (log, and ``on_change`` for the diagnostics) and retries opening it with
exponential back-off (``Backoff``); ``wait_for_port`` makes a board missing at start the
same wait instead of an error. With ``port`` = ``sim`` the board emulator runs on a
pseudo-terminal in this process; ``control`` names the control socket of a
``board_emulator`` process, through which a replaying camera sees what it has lit.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum

from fingerps_driver.board.backoff import Backoff
from fingerps_driver.board.board_emulator import BoardEmulator
from fingerps_driver.board.board_protocol import LED_COUNT, mask_to_indices
from fingerps_driver.board.emulator_control_client import BoardEmulatorControl
from fingerps_driver.board.led_board import BAUDRATE, RETRIES, TIMEOUT_S, LedBoard
from fingerps_driver.errors import (
    BoardError,
    BoardUnsupportedError,
    FingerpsDriverError,
    WrongBoardError,
)
from fingerps_ros.log import Log

SIM_PORT = "sim"
"""``port`` of the built-in board emulator."""

StartTimer = Callable[[float, Callable[[], None]], None]
"""``start_timer(delay_s, callback)``: call ``callback`` once, ``delay_s`` from now."""


class BoardState(Enum):
    """Connection state of the LED board."""

    CONNECTED = "connected"
    DISCONNECTED = "disconnected"  # lost while running; reconnecting
    WAITING = "waiting"  # not there at start (wait_for_port); retrying


@dataclass(frozen=True)
class BoardSettings:
    """The driver's board parameters.

    Attributes
    ----------
    port : str
        Serial device, or ``SIM_PORT`` for the built-in emulator.
    led_count : int
        LEDs the driver uses; the board must have at least as many.
    baudrate, timeout_s, retries
        Passed to ``LedBoard``.
    wait_for_port : bool
        A board missing at start is waited for instead of an error.
    backoff : Backoff
        Delays between attempts to reopen the board.
    control : str
        Control socket of a ``board_emulator`` process, or empty.
    trigger_delay_us, trigger_width_us : int
        The camera trigger (``LedBoard.trigger``), set at every connect; width 0: off.
    """

    port: str = SIM_PORT
    led_count: int = LED_COUNT
    baudrate: int = BAUDRATE
    timeout_s: float = TIMEOUT_S
    retries: int = RETRIES
    wait_for_port: bool = False
    backoff: Backoff = field(default_factory=lambda: Backoff(0.5, 5.0))
    control: str = ""
    trigger_delay_us: int = 0
    trigger_width_us: int = 0


class BoardConnection:
    """The LED board, its connection state and its counters.

    Parameters
    ----------
    settings : BoardSettings
        What to open.
    log : Log
        The node's logger.
    lock : threading.Lock
        Held while a reconnect attempt talks to the board (the bursts hold it too).
    start_timer : StartTimer
        Schedules the next reconnect attempt.
    on_change : callable
        Called after the board is lost and after it is back (the node publishes its
        diagnostics).
    clock : callable
        Monotonic seconds.
    """

    def __init__(self, settings: BoardSettings, *, log: Log, lock: threading.Lock,
                 start_timer: StartTimer, on_change: Callable[[], None] = lambda: None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings
        self.emulator: BoardEmulator | None = None
        self.control: BoardEmulatorControl | None = None
        self.led_board: LedBoard | None = None
        self.state = BoardState.DISCONNECTED
        self.firmware = ""
        self.error = ""
        """The last board error (empty while connected)."""
        self.disconnects = 0
        self.reconnects = 0
        self.reconnect_attempts = 0
        self.next_attempt = 0.0
        """``clock()`` of the next reconnect attempt."""
        self._log, self._lock, self._start_timer = log, lock, start_timer
        self._on_change, self._clock = on_change, clock
        self._pending = False
        self._closed = False

    @property
    def emulated(self) -> bool:
        """True if an emulator (built-in, or a process's control socket) shows the LEDs."""
        return self.emulator is not None or self.control is not None

    def open(self) -> BoardError | None:
        """Start the emulator (port sim), open the board and check it.

        Returns
        -------
        BoardError or None
            Why the board is missing, when ``wait_for_port`` says to wait for it (see
            ``wait``); None when connected.

        Raises
        ------
        FingerpsDriverError
            The board cannot be used (and is not to be waited for).
        """
        settings = self.settings
        port = settings.port
        if port == SIM_PORT:
            self.emulator = BoardEmulator(settings.led_count)
            self.emulator.start()
            port = self.emulator.port
        if settings.control:
            self.control = BoardEmulatorControl(settings.control, timeout_s=1.0)
        self.led_board = LedBoard(port, baudrate=settings.baudrate,
                                  timeout_s=settings.timeout_s, retries=settings.retries)
        try:
            self._connect()
        except BoardError as exc:
            if not settings.wait_for_port or isinstance(exc, WrongBoardError):
                raise FingerpsDriverError(
                    f"cannot use the LED board: {exc} (or use port:=sim for the simulated "
                    "rig, or wait_for_port:=true to wait for it)") from None
            return exc
        return None

    def wait(self, missing: BoardError) -> None:
        """Say that the board is waited for (``open`` returned ``missing``)."""
        assert self.led_board is not None
        self.state = BoardState.WAITING
        self.error = str(missing)
        self._log.warning(f"waiting for the LED board on {self.led_board.port}: {missing}")

    def start(self) -> None:
        """Start reconnecting if the board is not connected (the node is ready)."""
        if self.state is not BoardState.CONNECTED:
            self.schedule_reconnect()

    def _connect(self) -> None:
        """Open the port, check the board, switch everything off, set the camera trigger;
        raises ``BoardError``."""
        board = self.led_board
        assert board is not None
        settings = self.settings
        led_count = settings.led_count
        try:
            board.open()
            info = board.info()
            if info.led_count < led_count:
                raise WrongBoardError(
                    f"the board on {board.port!r} has {info.led_count} LEDs but led_count is "
                    f"{led_count}; set led_count to at most {info.led_count}")
            board.all_off()
            self._set_trigger(board)
        except BoardError:
            board.close()
            raise
        self.firmware = info.firmware
        self.state = BoardState.CONNECTED
        self.error = ""

    def _set_trigger(self, board: LedBoard) -> None:
        """Send the trigger setting; off (width 0) is also sent, so that no pulse is left
        from an earlier run, but a board without a trigger is fine then."""
        delay_us, width_us = self.settings.trigger_delay_us, self.settings.trigger_width_us
        try:
            board.trigger(delay_us, width_us)
        except BoardUnsupportedError:
            if width_us:
                raise WrongBoardError(
                    f"the board on {board.port!r} has no camera trigger (its firmware answers "
                    f"TRIG with ERR,CMD) but trigger_width_us is {width_us}: flash the "
                    "fingerps firmware (docs/board_firmware.md) or set trigger_width_us to 0"
                ) from None

    @property
    def lit_leds(self) -> Callable[[], Sequence[int]]:
        """What the replaying cameras (sim, folder) ask for the LEDs lit now."""
        if self.control is not None:
            return self.control.lit_leds
        if self.emulator is not None:
            return self.emulator.lit_leds

        def acknowledged() -> tuple[int, ...]:
            board = self.led_board
            mask = board.acknowledged_mask if board is not None else None
            if mask is None:
                raise FingerpsDriverError("the board has acknowledged no switch yet")
            return mask_to_indices(mask)
        return acknowledged

    def wait_s(self) -> float:
        """Seconds until the next reconnect attempt (0 when due)."""
        return max(0.0, self.next_attempt - self._clock())

    def not_connected_reason(self) -> str:
        """Why a burst asked for now is refused."""
        assert self.led_board is not None
        state = ("is not there yet" if self.state is BoardState.WAITING
                 else "is disconnected")
        return (f"no burst: the LED board on {self.led_board.port} {state} ({self.error}); "
                f"reconnecting, next attempt in {self.wait_s():.1f} s")

    def lost(self, reason: str) -> None:
        """The board vanished: close it, report it, start reconnecting."""
        assert self.led_board is not None
        self.led_board.close()
        self.state = BoardState.DISCONNECTED
        self.disconnects += 1
        self.error = reason
        self.reconnect_attempts = 0
        backoff = self.settings.backoff
        self._log.error(
            f"LED board on {self.led_board.port} lost: {reason}; reconnecting with back-off "
            f"({backoff.initial_s:g} s .. {backoff.max_s:g} s)")
        self.schedule_reconnect()
        self._on_change()

    def lose_if_port_vanished(self) -> bool:
        """Report the board lost if its device node is gone (USB unplugged, link removed).

        Returns True if it was (``on_change`` has been called then).
        """
        assert self.led_board is not None
        if self.state is BoardState.CONNECTED and not os.path.exists(self.led_board.port):
            self.lost(f"port {self.led_board.port} vanished")
            return True
        return False

    def schedule_reconnect(self) -> None:
        """Start the timer of the next attempt, unless one is pending or the board closed."""
        if self._pending or self._closed:
            return
        delay = self.settings.backoff.delay_s(self.reconnect_attempts)
        self.next_attempt = self._clock() + delay
        self._pending = True
        self._start_timer(delay, self.try_reconnect)

    def try_reconnect(self) -> None:
        """One attempt to reopen the board (the timer's callback)."""
        self._pending = False
        if self._closed or self.state is BoardState.CONNECTED:
            return
        self.reconnect_attempts += 1
        with self._lock:
            try:
                self._connect()
            except BoardError as exc:
                self.error = str(exc)
                self._log.warning(
                    f"LED board still unavailable (attempt {self.reconnect_attempts}): {exc}",
                    throttle_duration_sec=10.0)
                self.schedule_reconnect()
                return
        self.reconnects += 1
        assert self.led_board is not None
        self._log.info(
            f"LED board on {self.led_board.port} connected ({self.firmware}) after "
            f"{self.reconnect_attempts} attempt(s)")
        self.reconnect_attempts = 0
        self._on_change()

    def close(self) -> None:
        """Stop reconnecting, LEDs off, close the board, the control socket and the
        emulator (idempotent)."""
        self._closed = True
        board = self.led_board
        if board is not None and board.is_open:
            try:
                board.all_off()
            except (FingerpsDriverError, OSError) as exc:
                self._log.warning(f"could not switch the LEDs off: {exc}")
        if board is not None:
            board.close()
        if self.control is not None:
            self.control.close()
        if self.emulator is not None:
            self.emulator.stop()
