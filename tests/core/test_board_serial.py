"""LedBoard over pyserial against the BoardEmulator on a real pseudo-terminal."""

import os
import signal

import pytest

from fingerps_driver.board.board_emulator import BoardEmulator, Fault
from fingerps_driver.board.board_protocol import ErrorCode
from fingerps_driver.board.led_board import BoardInfo, LedBoard
from fingerps_driver.errors import (
    BoardDisconnectedError,
    BoardEmulatorError,
    BoardError,
    BoardNotFoundError,
    BoardProtocolError,
    BoardRejectedError,
    BoardTimeoutError,
)

TIMEOUT_S = 0.05
pytestmark = pytest.mark.usefixtures("no_emulator_threads_left")


@pytest.fixture
def board(emulator):
    with LedBoard(emulator.port, timeout_s=TIMEOUT_S, retries=2) as client:
        yield client


def test_emulator_serves_a_pty_behind_the_link(emulator, emulator_threads, tmp_path):
    assert emulator.port == str(tmp_path / "board")
    assert emulator.device.startswith("/dev/pts/")
    assert os.readlink(tmp_path / "board") == emulator.device
    assert len(emulator_threads()) == 1


def test_info_ping_and_levels(board, emulator):
    assert board.info() == BoardInfo("fingerps-emu-1.0", 7)
    assert board.ping() < TIMEOUT_S
    board.set_level(2, 100)
    assert emulator.levels == (255, 255, 100, 255, 255, 255, 255)
    assert board.state().levels == emulator.levels


def test_switching_each_led_lights_exactly_it(board, emulator):
    for led in range(7):
        assert board.set_leds(1 << led) == 1 << led
        assert emulator.lit_mask == 1 << led
        assert emulator.lit_leds() == (led,)
        assert board.state().mask == 1 << led
    assert board.set_leds(0b1010101) == 0b1010101
    assert emulator.lit_mask == 0b1010101
    board.all_off()
    assert emulator.lit_mask == 0
    masks = [mask for _, mask in emulator.history]
    assert masks == [1 << led for led in range(7)] + [0b1010101, 0]
    stamps = [t for t, _ in emulator.history]
    assert stamps == sorted(stamps)
    assert board.resends == 0


def test_out_of_range_is_rejected_not_retried(board, emulator):
    board.set_leds(0b1)
    requests = emulator.request_count
    with pytest.raises(BoardRejectedError) as info:
        board.set_leds(1 << 7)
    assert info.value.code is ErrorCode.OUT_OF_RANGE
    assert emulator.request_count == requests + 1
    assert emulator.lit_mask == 0b1
    with pytest.raises(BoardRejectedError):
        board.set_level(7, 10)
    with pytest.raises(ValueError):
        board.set_level(0, 256)


def test_dropped_reply_is_retried(board, emulator):
    requests = emulator.request_count
    emulator.inject(Fault.DROP_REPLY)
    assert board.set_leds(1 << 3) == 1 << 3
    assert emulator.lit_mask == 1 << 3
    assert board.resends == 1
    assert emulator.request_count == requests + 2


def test_corrupted_reply_is_retried(board, emulator):
    emulator.inject(Fault.CORRUPT_BYTE)
    assert board.set_leds(1 << 4) == 1 << 4
    assert emulator.lit_mask == 1 << 4
    assert board.resends == 1


def test_slow_reply_beyond_timeout_is_retried_and_the_late_reply_ignored(board, emulator):
    assert emulator.lit_mask == 0
    emulator.inject(Fault.SLOW_REPLY)
    assert board.set_leds(1 << 5) == 1 << 5
    resends = board.resends
    assert resends >= 1  # 1 normally; 2 if the machine is very busy
    # the stale reply of the first attempt must not be taken for the next answer
    assert board.set_leds(1 << 6) == 1 << 6
    assert board.info().led_count == 7
    assert board.resends == resends


def test_more_dropped_replies_than_retries_times_out(board, emulator):
    emulator.inject(Fault.DROP_REPLY, 3)
    with pytest.raises(BoardTimeoutError, match="3 attempt"):
        board.set_leds(1)
    assert board.set_leds(2) == 2  # the board is usable again


def test_more_corrupted_replies_than_retries_is_a_protocol_error(board, emulator):
    emulator.inject(Fault.CORRUPT_BYTE, 3)
    with pytest.raises(BoardProtocolError):
        board.ping()
    board.ping()


def test_disconnect_then_reconnect(tmp_path, emulator, board):
    board.set_leds(1 << 2)
    emulator.inject(Fault.DISCONNECT)
    assert not emulator.connected
    assert emulator.lit_mask == 0  # the board lost power
    assert not (tmp_path / "board").exists()
    with pytest.raises(BoardDisconnectedError, match="vanished"):
        board.set_leds(1 << 3)
    assert not board.is_open
    board.close()  # idempotent after the failure
    with pytest.raises(BoardNotFoundError):
        LedBoard(emulator.port).open()

    emulator.reconnect()
    assert emulator.connected
    with LedBoard(emulator.port, timeout_s=TIMEOUT_S) as fresh:
        assert fresh.set_leds(1 << 3) == 1 << 3
    board.open()  # the old client reopens the same (link) path
    assert board.set_leds(1 << 1) == 1 << 1
    assert emulator.lit_mask == 1 << 1


def test_missing_port_names_the_path(tmp_path):
    path = str(tmp_path / "no_such_board")
    with pytest.raises(BoardNotFoundError) as info:
        LedBoard(path).open()
    assert path in str(info.value)
    assert "board_emulator" in str(info.value)


def test_commands_need_an_open_port(emulator):
    client = LedBoard(emulator.port)
    with pytest.raises(BoardError, match="open"):
        client.ping()
    client.close()
    client.close()


def test_stop_is_idempotent_and_removes_the_link(emulator_threads, tmp_path):
    emu = BoardEmulator(link_path=str(tmp_path / "link"))
    emu.stop()  # before start: harmless
    emu.start()
    with pytest.raises(BoardEmulatorError):
        emu.start()
    assert (tmp_path / "link").is_symlink()
    emu.stop()
    emu.stop()
    assert not (tmp_path / "link").exists()
    assert emulator_threads() == []


def test_link_path_never_clobbers_a_regular_file(tmp_path):
    path = tmp_path / "precious"
    path.write_text("keep me")
    with pytest.raises(BoardEmulatorError, match="not a symlink"):
        BoardEmulator(link_path=str(path)).start()
    assert path.read_text() == "keep me"


def test_set_leds_round_trips_are_acknowledged_in_order_without_resends(board, emulator):
    # The round trip's time is a benchmark figure (bench/bench_driver.py,
    # driver.set_leds_ms.median); here: one request per switch, each acknowledged and
    # applied in order.
    requests = emulator.request_count
    masks = [1 << (i % 7) for i in range(300)]
    acknowledged = [board.set_leds(mask) for mask in masks]
    assert acknowledged == masks
    assert emulator.request_count - requests == len(masks)
    assert [mask for _, mask in emulator.history[-100:]] == masks[-100:]
    assert emulator.lit_mask == masks[-1]
    assert board.resends == 0


def test_console_script_serves_until_sigterm(tmp_path, emulator_script):
    link = tmp_path / "cli_board"
    process = emulator_script("--link", str(link))
    assert "Ctrl-C" in process.stdout.readline()
    with LedBoard(str(link)) as client:
        assert client.set_leds(1 << 6) == 1 << 6
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=5) == 0
    assert not link.exists()
