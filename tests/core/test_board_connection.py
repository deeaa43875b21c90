"""BoardConnection without ROS: opening and checking the board, waiting for it, losing it,
reconnecting with back-off, a vanished port, closing; against the BoardEmulator on a pty.

A ``Mock`` stands in for the node's logger (its ``method_calls`` are the lines), ``Timers``
for the node's timers, here and in the other driver core tests.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from unittest.mock import Mock

import pytest

from fingerps_driver.board.backoff import Backoff
from fingerps_driver.board.board_connection import (
    SIM_PORT,
    BoardConnection,
    BoardSettings,
    BoardState,
)
from fingerps_driver.board.board_emulator import BoardEmulator
from fingerps_driver.errors import FingerpsDriverError


def said(log: Mock, level: str, text: str) -> bool:
    """True if ``log`` (a Mock standing in for the node's logger) had a line at ``level``
    containing ``text``."""
    return any(name == level and text in args[0] for name, args, _ in log.method_calls)


class Timers:
    """One-shot timers the test fires by hand: (delay, callback) in the order started."""

    def __init__(self) -> None:
        self.started: list[tuple[float, Callable[[], None]]] = []

    def __call__(self, delay_s: float, callback: Callable[[], None]) -> None:
        self.started.append((delay_s, callback))

    def fire(self) -> None:
        """Run the oldest timer not yet fired."""
        _, callback = self.started.pop(0)
        callback()


class Clock:
    """A monotonic clock the test sets."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


pytestmark = pytest.mark.usefixtures("no_emulator_threads_left")


def _connection(settings: BoardSettings, log: Mock, timers: Timers,
                changes: list[str] | None = None, clock: Clock | None = None
                ) -> BoardConnection:
    return BoardConnection(
        settings, log=log, lock=threading.Lock(), start_timer=timers,
        on_change=(lambda: changes.append("change")) if changes is not None else lambda: None,
        **({"clock": clock} if clock is not None else {}))


def test_the_built_in_emulator_is_opened_checked_and_closed():
    log, timers = Mock(), Timers()
    board = _connection(BoardSettings(port=SIM_PORT, led_count=7), log, timers)
    try:
        assert board.open() is None
        assert board.state is BoardState.CONNECTED
        assert board.firmware == "fingerps-emu-1.0" and board.error == ""
        assert board.emulated and board.led_board is not None and board.led_board.is_open
        assert board.led_board.port == board.emulator.port
        assert board.lit_leds() == ()
        assert board.led_board.set_leds(0b100) == 0b100
        assert board.lit_leds() == (2,)
        board.start()
        assert timers.started == []  # connected: nothing to retry
    finally:
        board.close()
    assert not board.led_board.is_open
    board.close()  # idempotent


def test_a_missing_board_is_an_error_unless_waited_for(tmp_path):
    log, timers = Mock(), Timers()
    link = str(tmp_path / "board")
    board = _connection(BoardSettings(port=link), log, timers)
    with pytest.raises(FingerpsDriverError, match=r"cannot use the LED board: LED board port "
                       r".* does not exist.*\(or use port:=sim for the simulated rig, or "
                       r"wait_for_port:=true to wait for it\)"):
        board.open()
    board.close()


def test_a_board_with_too_few_leds_is_refused_even_when_waiting(tmp_path):
    log, timers = Mock(), Timers()
    with BoardEmulator(5, link_path=str(tmp_path / "board")) as emulator:
        board = _connection(BoardSettings(port=emulator.port, wait_for_port=True), log, timers)
        with pytest.raises(FingerpsDriverError,
                           match="has 5 LEDs but led_count is 7; set led_count to at most 5"):
            board.open()
        assert not board.led_board.is_open
        board.close()


def test_a_board_waited_for_is_retried_with_back_off_until_it_comes(tmp_path):
    log, timers, clock, changes = Mock(), Timers(), Clock(), []
    link = str(tmp_path / "board")
    settings = BoardSettings(port=link, wait_for_port=True, backoff=Backoff(0.5, 1.5))
    board = _connection(settings, log, timers, changes, clock)
    missing = board.open()
    assert missing is not None and board.state is BoardState.DISCONNECTED
    board.wait(missing)
    assert board.state is BoardState.WAITING and "does not exist" in board.error
    assert said(log, "warning", f"waiting for the LED board on {link}: ")
    board.start()
    assert [d for d, _ in timers.started] == [0.5]
    clock.now += 0.2
    reason = board.not_connected_reason()
    assert reason.startswith(f"no burst: the LED board on {link} is not there yet (")
    assert reason.endswith("; reconnecting, next attempt in 0.3 s")
    board.start()  # a timer is pending already: no second one
    assert len(timers.started) == 1
    for attempt, delay in ((1, 1.0), (2, 1.5), (3, 1.5)):  # doubled, capped at max_s
        timers.fire()
        assert board.reconnect_attempts == attempt
        assert [d for d, _ in timers.started] == [delay]
    assert said(log, "warning", "LED board still unavailable (attempt 3): ")
    with BoardEmulator(7, link_path=link):
        timers.fire()
        assert board.state is BoardState.CONNECTED and board.error == ""
        assert (board.reconnects, board.reconnect_attempts, board.disconnects) == (1, 0, 0)
        assert said(log, "info", f"LED board on {link} connected (fingerps-emu-1.0) after 4 "
                                "attempt(s)")
        assert changes == ["change"] and timers.started == []
        board.close()


def test_a_lost_board_is_reported_and_reopened(tmp_path):
    log, timers, changes = Mock(), Timers(), []
    link = str(tmp_path / "board")
    with BoardEmulator(7, link_path=link) as emulator:
        board = _connection(BoardSettings(port=link), log, timers, changes)
        assert board.open() is None
        emulator.disconnect()
        board.lost("burst 3 failed")
        assert board.state is BoardState.DISCONNECTED and not board.led_board.is_open
        assert (board.disconnects, board.error) == (1, "burst 3 failed")
        assert said(log, "error", f"LED board on {link} lost: burst 3 failed; reconnecting "
                                 "with back-off (0.5 s .. 5 s)")
        assert changes == ["change"] and [d for d, _ in timers.started] == [0.5]
        assert "is disconnected (burst 3 failed)" in board.not_connected_reason()
        timers.fire()  # still away
        assert board.reconnect_attempts == 1 and [d for d, _ in timers.started] == [1.0]
        emulator.reconnect()
        timers.fire()
        assert board.state is BoardState.CONNECTED and board.reconnects == 1
        assert changes == ["change", "change"]
        board.close()


def test_a_vanished_port_is_a_loss(tmp_path):
    log, timers = Mock(), Timers()
    link = str(tmp_path / "board")
    with BoardEmulator(7, link_path=link) as emulator:
        board = _connection(BoardSettings(port=link), log, timers)
        board.open()
        assert not board.lose_if_port_vanished()
        emulator.disconnect()  # removes the link
        assert not os.path.exists(link)
        assert board.lose_if_port_vanished()
        assert board.error == f"port {link} vanished" and board.state is BoardState.DISCONNECTED
        assert not board.lose_if_port_vanished()  # reported once
        board.close()


def test_a_closed_connection_stops_reconnecting(tmp_path):
    log, timers = Mock(), Timers()
    link = str(tmp_path / "board")
    with BoardEmulator(7, link_path=link):
        board = _connection(BoardSettings(port=link), log, timers)
        board.open()
        board.lost("cable")
        board.close()
        timers.fire()  # the pending attempt does nothing
        assert board.state is BoardState.DISCONNECTED and board.reconnect_attempts == 0
        board.schedule_reconnect()
        assert timers.started == []


def test_the_trigger_is_set_at_connect_and_again_after_a_reconnect(tmp_path):
    log, timers = Mock(), Timers()
    link = str(tmp_path / "board")
    with BoardEmulator(7, link_path=link) as emulator:
        settings = BoardSettings(port=link, trigger_delay_us=100, trigger_width_us=50)
        board = _connection(settings, log, timers)
        assert board.open() is None
        assert emulator.trigger == (100, 50)
        emulator.disconnect()  # power lost: the board's trigger is off again
        assert emulator.trigger == (0, 0)
        board.lost("cable")
        emulator.reconnect()
        timers.fire()
        assert board.state is BoardState.CONNECTED and emulator.trigger == (100, 50)
        board.close()


def test_a_trigger_left_on_by_an_earlier_run_is_switched_off(tmp_path):
    log, timers = Mock(), Timers()
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emulator:
        board = _connection(BoardSettings(port=emulator.port, trigger_delay_us=100,
                                          trigger_width_us=50), log, timers)
        board.open()
        board.close()
        assert emulator.trigger == (100, 50)  # a board keeps it over a new connection
        board = _connection(BoardSettings(port=emulator.port), log, timers)
        board.open()
        assert emulator.trigger == (0, 0)
        board.close()


def test_a_board_without_a_trigger_is_refused_only_when_one_is_asked_for(tmp_path):
    log, timers = Mock(), Timers()
    with BoardEmulator(7, link_path=str(tmp_path / "board"), with_trigger=False) as emulator:
        board = _connection(BoardSettings(port=emulator.port, wait_for_port=True,
                                          trigger_width_us=20), log, timers)
        with pytest.raises(FingerpsDriverError, match=(
                r"has no camera trigger \(its firmware answers TRIG with ERR,CMD\) but "
                "trigger_width_us is 20: flash the fingerps firmware")):
            board.open()
        assert not board.led_board.is_open
        board.close()
        board = _connection(BoardSettings(port=emulator.port), log, timers)
        assert board.open() is None and board.state is BoardState.CONNECTED
        board.close()


def test_without_an_emulator_the_acknowledged_mask_is_what_is_lit(tmp_path):
    log, timers = Mock(), Timers()
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emulator:
        board = _connection(BoardSettings(port=emulator.port), log, timers)
        assert not board.emulated
        lit = board.lit_leds
        with pytest.raises(FingerpsDriverError, match="acknowledged no switch yet"):
            lit()
        board.open()  # switches all off: acknowledged
        assert lit() == ()
        board.led_board.set_leds(0b1010)
        assert lit() == (1, 3)
        board.close()
