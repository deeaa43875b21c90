"""FrameReader: the one framing loop of LedBoard and BoardEmulator, on a pipe."""

from __future__ import annotations

import os
import threading
import time
from functools import partial

import pytest

from fingerps_driver.board.board_protocol import REPLY_SIGIL
from fingerps_driver.board.frame_reader import FrameReader


@pytest.fixture
def pipe():
    read_fd, write_fd = os.pipe()
    yield read_fd, write_fd
    os.close(read_fd)
    os.close(write_fd)


def _reader(read_fd: int, **kwargs) -> FrameReader:
    return FrameReader(read_fd, partial(os.read, read_fd), REPLY_SIGIL, **kwargs)


def test_lines_resync_on_garbage_and_keep_a_partial_line(pipe):
    read_fd, write_fd = pipe
    reader = _reader(read_fd)
    os.write(write_fd, b"noise!1,OK*AB\n!2,O")
    assert list(reader.lines(deadline=time.monotonic() + 0.05)) == [b"!1,OK*AB"]
    os.write(write_fd, b"K*CD\n")
    assert next(reader.lines(deadline=time.monotonic() + 1.0)) == b"!2,OK*CD"


def test_reset_forgets_the_partial_line(pipe):
    read_fd, write_fd = pipe
    reader = _reader(read_fd)
    os.write(write_fd, b"!7,O")
    assert list(reader.lines(deadline=time.monotonic() + 0.02)) == []
    reader.reset()
    os.write(write_fd, b"K*00\n!8,OK*00\n")
    assert next(reader.lines(deadline=time.monotonic() + 1.0)) == b"!8,OK*00"


def test_a_deadline_ends_the_wait(pipe):
    reader = _reader(pipe[0])
    start = time.monotonic()
    assert list(reader.lines(deadline=start + 0.03)) == []
    assert time.monotonic() - start >= 0.03  # it waited its deadline out


def test_the_wake_descriptor_ends_a_stopped_wait_at_once(pipe):
    wake_r, wake_w = os.pipe()
    stop = threading.Event()
    reader = _reader(pipe[0], wake_fd=wake_r)

    def wake() -> None:
        stop.set()
        os.write(wake_w, b"x")

    timer = threading.Timer(0.02, wake)
    timer.start()
    try:
        assert list(reader.lines(stop=stop)) == []
    finally:
        timer.join()
        os.close(wake_r)
        os.close(wake_w)


def test_read_errors_reach_the_caller(pipe):
    read_fd, write_fd = pipe

    def vanished(size: int) -> bytes:
        raise OSError(5, "Input/output error")

    os.write(write_fd, b"x")
    with pytest.raises(OSError, match="Input/output"):
        list(FrameReader(read_fd, vanished, REPLY_SIGIL).lines(deadline=time.monotonic() + 1))
