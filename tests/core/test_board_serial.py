"""LedBoard over pyserial against a board on a real pseudo-terminal.

The protocol tests run against both boards (``board_port``: the Python ``BoardEmulator``
and the AVR firmware under simavr): commands, levels, STATE, every error code, resends, a
garbled and an overlong line. The fault-injection tests need the emulator's control and run
against it only (``emulated_board``).
"""

import os
import signal

import pytest
from board_lines import BAD_LINES, RawBoard, request_line

from fingerps_driver import errors
from fingerps_driver.board.board_emulator import BoardEmulator, Fault
from fingerps_driver.board.board_protocol import (
    MAX_LINE_BYTES,
    ErrorCode,
    Reply,
    crc8,
    decode_reply,
)
from fingerps_driver.board.led_board import BoardInfo, LedBoard, LedState

TIMEOUT_S = 0.05
pytestmark = pytest.mark.usefixtures("no_emulator_threads_left")


@pytest.fixture
def board(board_port):
    """LedBoard on either board (the simulated chip's time follows the host's clock, so a
    busy host delays its replies: a longer timeout, only reached on a failure)."""
    timeout_s = TIMEOUT_S if board_port.kind == "emulator" else 0.5
    with LedBoard(board_port.port, timeout_s=timeout_s, retries=2) as client:
        yield client


@pytest.fixture
def emulated_board(emulator):
    """LedBoard on the emulator (the tests that inject faults)."""
    with LedBoard(emulator.port, timeout_s=TIMEOUT_S, retries=2) as client:
        yield client


@pytest.fixture
def raw(board_port):
    """Raw request lines to either board (``board_lines.RawBoard``)."""
    with RawBoard(board_port.port) as port:
        yield port


def test_emulator_serves_a_pty_behind_the_link(emulator, emulator_threads, tmp_path):
    assert emulator.port == str(tmp_path / "board")
    assert emulator.device.startswith("/dev/pts/")
    assert os.readlink(tmp_path / "board") == emulator.device
    assert len(emulator_threads()) == 1


def test_info_ping_and_levels(board, board_port):
    assert board.info() == BoardInfo(board_port.firmware, 7)
    board.ping()
    assert board.state() == LedState(0, (255,) * 7)  # off, full level at power-up
    board.set_level(2, 100)
    board.set_level(6, 0)
    assert board.state().levels == (255, 255, 100, 255, 255, 255, 0)
    if board_port.emulator is not None:
        assert board_port.emulator.levels == board.state().levels
    board.set_leds(0b1000100)  # a lit LED at level 100 and one at 0 are still "lit"
    assert board.state() == LedState(0b1000100, (255, 255, 100, 255, 255, 255, 0))
    board.set_level(2, 255)
    assert board.state().levels[2] == 255
    assert board.resends == 0


def test_switching_each_led_lights_exactly_it(board, board_port):
    for led in range(7):
        assert board.set_leds(1 << led) == 1 << led
        assert board.state().mask == 1 << led
    assert board.set_leds(0b1010101) == 0b1010101
    assert board.state().mask == 0b1010101
    board.all_off()
    assert board.state().mask == 0
    assert board.resends == 0
    if board_port.emulator is not None:  # what it physically lit (the firmware's pins:
        emulator = board_port.emulator    # test_board_firmware, from the trace)
        masks = [mask for _, mask in emulator.history]
        assert masks == [1 << led for led in range(7)] + [0b1010101, 0]
        stamps = [t for t, _ in emulator.history]
        assert stamps == sorted(stamps)


def test_out_of_range_is_rejected_not_retried(board):
    board.set_leds(0b1)
    with pytest.raises(errors.BoardRejectedError) as info:
        board.set_leds(1 << 7)
    assert info.value.code is ErrorCode.OUT_OF_RANGE
    assert board.resends == 0  # one request, not resent
    assert board.state().mask == 0b1
    with pytest.raises(errors.BoardRejectedError) as info:
        board.set_level(7, 10)
    assert info.value.code is ErrorCode.OUT_OF_RANGE
    with pytest.raises(ValueError):
        board.set_level(0, 256)
    assert board.resends == 0 and board.state().levels == (255,) * 7


def test_every_error_code_is_answered_with_the_seq(raw):
    for line, code in BAD_LINES:
        [(_, answer)] = raw.send(line)
        reply = decode_reply(answer)
        assert (reply.seq, reply.error) == (9, code), (line, answer)
        assert reply.message and reply.message != "-"
    assert raw.quiet() == RawBoard.sentinel_reply()
    [(_, answer)] = raw.send(request_line("10,STATE"))
    assert decode_reply(answer) == Reply(10, ("00",) + ("255",) * 7)  # nothing was applied


def test_resends_with_new_seqs_are_answered_and_idempotent(raw):
    for seq in (254, 255, 0, 1):  # the host's resends of one switch, seq wrapping
        [(_, answer)] = raw.send(request_line(f"{seq},LEDS,05"))
        assert decode_reply(answer) == Reply(seq, ("05",))
    replies = raw.send(request_line("2,LEVEL,0,7") + request_line("3,LEVEL,0,7"))
    assert [decode_reply(answer) for _, answer in replies] == [Reply(2), Reply(3)]
    [(_, first), (_, second)] = raw.send(request_line("4,STATE") + request_line("5,STATE"))
    assert decode_reply(first).values == decode_reply(second).values
    assert decode_reply(first).values == ("05", "7") + ("255",) * 6
    # a lower-case checksum and a CR before the newline are accepted
    [(_, answer)] = raw.send(b"#6,PING*" + f"{crc8(b'6,PING'):02x}".encode() + b"\r\n")
    assert decode_reply(answer) == Reply(6)


def test_garbled_lines_get_no_reply_and_the_board_resynchronises(raw):
    silent = [
        b"noise without a sigil\n",
        b"#9,PING\n",  # no star: nothing is known to be the seq
        request_line("x,PING"),  # no readable seq
        request_line("256,PING"),
        request_line("0007,PING"),
        request_line(",PING"),
        b"#\n",
        b"#9,P\xc3\x9cNG*00\n",  # not ASCII
        b"!9,OK*00\n",  # a reply's sigil
    ]
    for line in silent:
        assert raw.send(line) == [], line
    assert raw.quiet() == RawBoard.sentinel_reply()
    # a sigil mid-line restarts the line: the first half is dropped, the second answered
    [(line, answer)] = raw.send(b"#12,LEDS,0" + request_line("13,LEDS,03"))
    assert line == request_line("13,LEDS,03")[:-1]
    assert decode_reply(answer) == Reply(13, ("03",))
    # noise before a sigil and a line split over two writes
    whole = request_line("14,STATE")
    assert raw.send(b"\x00\xff junk " + whole[:5]) == []
    [(_, answer)] = raw.send(whole[5:])
    assert decode_reply(answer).values[0] == "03"
    assert raw.quiet() == RawBoard.sentinel_reply()


def test_an_overlong_line_is_dropped_and_the_next_answered(raw):
    # 255 bytes, sigil included, newline excluded: the longest line; it is read (ARG: no
    # such mask), one byte more and it is dropped unanswered.
    padding = MAX_LINE_BYTES - len(request_line("15,LEDS,")) + 1
    longest = request_line("15,LEDS," + "0" * padding)
    assert len(longest) - 1 == MAX_LINE_BYTES
    [(_, answer)] = raw.send(longest)
    assert decode_reply(answer).error is ErrorCode.BAD_ARGUMENT
    assert raw.send(request_line("16,LEDS," + "0" * (padding + 1))) == []
    assert raw.send(b"#17,LEDS," + b"1" * 1000 + b"\n") == []
    assert raw.quiet() == RawBoard.sentinel_reply()
    [(_, answer)] = raw.send(request_line("18,LEDS,01"))
    assert decode_reply(answer) == Reply(18, ("01",))


def test_trigger_is_accepted_by_both_boards(board, board_port):
    board.trigger(100, 50)
    board.set_leds(0b11)
    board.trigger(0, 0)
    assert board.state().mask == 0b11  # TRIG itself switches nothing
    if board_port.emulator is not None:
        assert board_port.emulator.trigger == (0, 0)
    assert board.resends == 0


def test_trigger_is_set_and_an_older_board_says_it_has_none(emulated_board, emulator, tmp_path):
    assert emulator.trigger == (0, 0)  # off at power-up
    emulated_board.trigger(100, 50)
    assert emulator.trigger == (100, 50)
    emulated_board.trigger(0, 0)
    assert emulator.trigger == (0, 0)
    with pytest.raises(ValueError, match="width_us 65536 outside"):
        emulated_board.trigger(0, 65536)
    with BoardEmulator(link_path=str(tmp_path / "old"), with_trigger=False) as old, \
            LedBoard(old.port, timeout_s=TIMEOUT_S) as client:
        with pytest.raises(errors.BoardUnsupportedError, match="has no camera trigger") as info:
            client.trigger(100, 50)
        assert info.value.code is ErrorCode.UNKNOWN_COMMAND
        assert isinstance(info.value, errors.BoardRejectedError) and client.resends == 0
        assert client.set_leds(1) == 1  # the rest works


def test_dropped_reply_is_retried(emulated_board, emulator):
    requests = emulator.request_count
    emulator.inject(Fault.DROP_REPLY)
    assert emulated_board.set_leds(1 << 3) == 1 << 3
    assert emulator.lit_mask == 1 << 3
    assert emulated_board.resends == 1
    assert emulator.request_count == requests + 2


def test_corrupted_reply_is_retried(emulated_board, emulator):
    emulator.inject(Fault.CORRUPT_BYTE)
    assert emulated_board.set_leds(1 << 4) == 1 << 4
    assert emulator.lit_mask == 1 << 4
    assert emulated_board.resends == 1


def test_slow_reply_beyond_timeout_is_retried_and_the_late_reply_ignored(emulated_board,
                                                                         emulator):
    assert emulator.lit_mask == 0
    emulator.inject(Fault.SLOW_REPLY)
    assert emulated_board.set_leds(1 << 5) == 1 << 5
    resends = emulated_board.resends
    assert resends >= 1  # 1 normally; 2 if the machine is very busy
    # the stale reply of the first attempt must not be taken for the next answer
    assert emulated_board.set_leds(1 << 6) == 1 << 6
    assert emulated_board.info().led_count == 7
    assert emulated_board.resends == resends


def test_more_dropped_replies_than_retries_times_out(emulated_board, emulator):
    emulator.inject(Fault.DROP_REPLY, 3)
    with pytest.raises(errors.BoardTimeoutError, match="3 attempt"):
        emulated_board.set_leds(1)
    assert emulated_board.set_leds(2) == 2  # the board is usable again


def test_more_corrupted_replies_than_retries_is_a_protocol_error(emulated_board, emulator):
    emulator.inject(Fault.CORRUPT_BYTE, 3)
    with pytest.raises(errors.BoardProtocolError):
        emulated_board.ping()
    emulated_board.ping()


def test_disconnect_then_reconnect(tmp_path, emulator, emulated_board):
    emulated_board.set_leds(1 << 2)
    emulator.inject(Fault.DISCONNECT)
    assert not emulator.connected
    assert emulator.lit_mask == 0  # the board lost power
    assert not (tmp_path / "board").exists()
    with pytest.raises(errors.BoardDisconnectedError, match="vanished"):
        emulated_board.set_leds(1 << 3)
    assert not emulated_board.is_open
    emulated_board.close()  # idempotent after the failure
    with pytest.raises(errors.BoardNotFoundError):
        LedBoard(emulator.port).open()

    emulator.reconnect()
    assert emulator.connected
    with LedBoard(emulator.port, timeout_s=TIMEOUT_S) as fresh:
        assert fresh.set_leds(1 << 3) == 1 << 3
    emulated_board.open()  # the old client reopens the same (link) path
    assert emulated_board.set_leds(1 << 1) == 1 << 1
    assert emulator.lit_mask == 1 << 1


def test_missing_port_names_the_path(tmp_path):
    path = str(tmp_path / "no_such_board")
    with pytest.raises(errors.BoardNotFoundError) as info:
        LedBoard(path).open()
    assert path in str(info.value)
    assert "board_emulator" in str(info.value)


def test_commands_need_an_open_port(emulator):
    client = LedBoard(emulator.port)
    with pytest.raises(errors.BoardError, match="open"):
        client.ping()
    client.close()
    client.close()


def test_stop_is_idempotent_and_removes_the_link(emulator_threads, tmp_path):
    emu = BoardEmulator(link_path=str(tmp_path / "link"))
    emu.stop()  # before start: harmless
    emu.start()
    with pytest.raises(errors.BoardEmulatorError):
        emu.start()
    assert (tmp_path / "link").is_symlink()
    emu.stop()
    emu.stop()
    assert not (tmp_path / "link").exists()
    assert emulator_threads() == []


def test_link_path_never_clobbers_a_regular_file(tmp_path):
    path = tmp_path / "precious"
    path.write_text("keep me")
    with pytest.raises(errors.BoardEmulatorError, match="not a symlink"):
        BoardEmulator(link_path=str(path)).start()
    assert path.read_text() == "keep me"


def test_set_leds_round_trips_are_acknowledged_in_order_without_resends(board, board_port):
    # The round trip's time is a benchmark figure (bench/bench_driver.py,
    # driver.set_leds_ms.median); here: one request per switch, each acknowledged and
    # applied in order.
    emulator = board_port.emulator
    requests = emulator.request_count if emulator is not None else 0
    masks = [1 << (i % 7) for i in range(300)]
    acknowledged = [board.set_leds(mask) for mask in masks]
    assert acknowledged == masks
    assert board.state().mask == masks[-1]
    assert board.resends == 0
    if emulator is not None:
        assert emulator.request_count - requests == len(masks) + 1
        assert [mask for _, mask in emulator.history[-100:]] == masks[-100:]
        assert emulator.lit_mask == masks[-1]


def test_console_script_serves_until_sigterm(tmp_path, emulator_script):
    link = tmp_path / "cli_board"
    process = emulator_script("--link", str(link))
    assert "Ctrl-C" in process.stdout.readline()
    with LedBoard(str(link)) as client:
        assert client.set_leds(1 << 6) == 1 << 6
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=5) == 0
    assert not link.exists()
