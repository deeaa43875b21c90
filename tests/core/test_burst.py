"""capture_burst over the real serial path: LedBoard -> pty -> BoardEmulator -> camera."""

import threading
import time

import numpy as np
import pytest
from led_history import masks_lit_since, repeats_since

from fingerps_driver.board.board_emulator import BoardEmulator, Fault
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import Camera, SimulatedCamera
from fingerps_driver.capture.burst import DARK_LED, BurstResult, capture_burst
from fingerps_driver.errors import CameraError

H, W = 6, 8
LEDS = tuple(range(7))


def _render(lit):
    """Frame whose every pixel is the mask of the LEDs lit at grab time (uint16)."""
    return np.full((H, W), sum(1 << i for i in lit), dtype=np.uint16)


class _Rig:
    """Emulator, client and simulated camera wired as the driver node wires them."""

    def __init__(self, tmp_path, render=_render):
        self.emulator = BoardEmulator(7, link_path=str(tmp_path / "board"))
        self.emulator.start()
        self.board = LedBoard(self.emulator.port, timeout_s=0.05, retries=2)
        self.board.open()
        self.grab_hook = None
        self.render = render
        self.camera = SimulatedCamera(
            self._render, self.emulator.lit_leds, width=W, height=H, encoding="mono16"
        )
        self.camera.open()

    def _render(self, lit):
        if self.grab_hook is not None:
            self.grab_hook()
        return self.render(lit)

    def close(self):
        self.camera.close()
        self.board.close()
        self.emulator.stop()


@pytest.fixture
def rig(tmp_path):
    rig = _Rig(tmp_path)
    yield rig
    rig.close()
    assert not [t for t in threading.enumerate() if t.name == "board-emulator"]


def _burst(rig, burst_id=1, **options) -> BurstResult:
    kwargs = {"led_order": LEDS, "exposures_s": 0.01, "levels": 1.0, **options}
    return capture_burst(rig.board, rig.camera, burst_id=burst_id, **kwargs)


def test_simulated_camera_is_a_camera(rig):
    assert isinstance(rig.camera, Camera)


def test_burst_frames_are_tagged_with_the_led_actually_lit(rig):
    start, resends = time.monotonic(), rig.board.resends
    result = _burst(rig, burst_id=7, with_dark=True)
    assert result.ok, result.reason
    assert result.reason == ""
    assert result.burst_id == 7
    assert [f.led_index for f in result.frames] == list(LEDS)
    for frame in result.frames:
        # the pixels encode what the emulator had lit when the camera grabbed
        assert np.all(frame.image == 1 << frame.led_index)
        assert frame.image.shape == (H, W) and frame.image.dtype == np.uint16
        assert frame.exposure_s == 0.01 and frame.level == 1.0
    stamps = [f.stamp_ns for f in result.frames] + [result.dark.stamp_ns]
    assert stamps == sorted(stamps)
    assert result.dark.led_index == DARK_LED
    assert np.all(result.dark.image == 0) and result.dark.level == 0.0
    # the emulator switched exactly one LED at a time, in order, then all off
    assert masks_lit_since(rig.emulator.history, start) == [1 << i for i in LEDS] + [0]
    assert repeats_since(rig.emulator.history, start) <= rig.board.resends - resends
    assert rig.emulator.lit_mask == 0
    assert result.duration_s > 0.0  # measured; its size is bench/bench_driver.py's burst_ms


def test_order_levels_and_exposures_are_applied_and_tagged(rig):
    start, resends = time.monotonic(), rig.board.resends
    result = _burst(rig, led_order=(4, 0, 2), exposures_s=(0.01, 0.02, 0.03),
                    levels=(0.5, 1.0, 0.25))
    assert result.ok, result.reason
    assert result.dark is None
    assert [f.led_index for f in result.frames] == [4, 0, 2]
    assert [int(f.image[0, 0]) for f in result.frames] == [16, 1, 4]
    assert [f.exposure_s for f in result.frames] == [0.01, 0.02, 0.03]
    assert [f.level for f in result.frames] == [128 / 255, 1.0, 64 / 255]
    assert rig.emulator.levels == (255, 255, 64, 255, 128, 255, 255)
    assert masks_lit_since(rig.emulator.history, start) == [16, 1, 4, 0]
    assert repeats_since(rig.emulator.history, start) <= rig.board.resends - resends


def test_the_first_led_is_repeated_after_the_last_when_asked(rig):
    start, resends = time.monotonic(), rig.board.resends
    result = _burst(rig, led_order=(4, 0, 2), exposures_s=(0.01, 0.02, 0.03),
                    repeat_first=True, with_dark=True)
    assert result.ok, result.reason
    assert [f.led_index for f in result.frames] == [4, 0, 2]
    repeat = result.repeat
    assert repeat is not None and repeat.led_index == 4 and repeat.exposure_s == 0.01
    assert np.all(repeat.image == 16)  # LED 4 was lit again when the camera grabbed
    assert result.frames[-1].stamp_ns <= repeat.stamp_ns <= result.dark.stamp_ns
    assert masks_lit_since(rig.emulator.history, start) == [16, 1, 4, 16, 0]
    assert repeats_since(rig.emulator.history, start) <= rig.board.resends - resends
    assert _burst(rig).repeat is None


def test_fault_mid_burst_fails_it_and_the_next_burst_is_fine(rig):
    grabs = []

    def lose_the_next_replies():
        grabs.append(rig.emulator.lit_mask)
        if len(grabs) == 3:  # while LED 2 is lit: the switch to LED 3 gets no answer
            rig.emulator.inject(Fault.DROP_REPLY, 3)

    rig.grab_hook = lose_the_next_replies
    result = _burst(rig, burst_id=1)
    assert not result.ok
    assert result.frames == () and result.dark is None
    assert "switch" in result.reason and "LED 3" in result.reason
    assert "BoardTimeoutError" in result.reason
    assert rig.emulator.lit_mask == 0  # switched off after the failure

    rig.grab_hook = None
    start, resends = time.monotonic(), rig.board.resends
    result = _burst(rig, burst_id=2)
    assert result.ok, result.reason
    assert [int(f.image[0, 0]) for f in result.frames] == [1 << i for i in LEDS]
    assert masks_lit_since(rig.emulator.history, start) == [1 << i for i in LEDS] + [0]
    assert repeats_since(rig.emulator.history, start) <= rig.board.resends - resends


def test_disconnect_mid_burst_fails_it_and_a_reconnected_board_works(rig):
    calls = []

    def pull_the_cable():
        calls.append(1)
        if len(calls) == 2:
            rig.emulator.inject(Fault.DISCONNECT)

    rig.grab_hook = pull_the_cable
    result = _burst(rig)
    assert not result.ok
    assert "switch" in result.reason and "LED 2" in result.reason
    assert "BoardDisconnectedError" in result.reason

    rig.grab_hook = None
    rig.emulator.reconnect()
    rig.board.open()
    assert _burst(rig, burst_id=2).ok


def test_retried_fault_mid_burst_still_gives_a_correct_burst(rig):
    def corrupt_once():
        if rig.emulator.lit_mask == 1 << 4:
            rig.emulator.inject(Fault.CORRUPT_BYTE)

    rig.grab_hook = corrupt_once
    result = _burst(rig)
    assert result.ok, result.reason
    assert [int(f.image[0, 0]) for f in result.frames] == [1 << i for i in LEDS]
    assert rig.board.resends == 1


def test_wrong_frame_size_fails_the_burst(tmp_path):
    def small_render(lit):
        return np.zeros((H - 1, W), np.uint16)

    rig = _Rig(tmp_path, render=small_render)
    try:
        result = _burst(rig)
        assert not result.ok
        assert "grab" in result.reason and "LED 0" in result.reason
        assert "CameraError" in result.reason
        assert rig.emulator.lit_mask == 0
    finally:
        rig.close()


def test_unexpected_shape_fails_the_burst(rig):
    result = _burst(rig, expected_shape=(H, W + 1))
    assert not result.ok
    assert "LED 0" in result.reason and "shape" in result.reason
    assert result.frames == ()
    assert rig.emulator.lit_mask == 0


def test_camera_failure_mid_burst_fails_the_burst(rig):
    def fail_on_led_5():
        if rig.emulator.lit_mask == 1 << 5:
            raise RuntimeError("sensor readout error")

    rig.grab_hook = fail_on_led_5
    result = _burst(rig)
    assert not result.ok
    assert "grab" in result.reason and "LED 5" in result.reason
    assert rig.emulator.lit_mask == 0


def test_closed_camera_fails_the_burst(rig):
    rig.camera.close()
    result = _burst(rig)
    assert not result.ok and "open" in result.reason


class _WrongAckBoard:
    """A board that acknowledges a different mask than asked for (no exception)."""

    def __init__(self):
        self.off_calls = 0

    def set_leds(self, mask):
        return mask << 1

    def all_off(self):
        self.off_calls += 1

    def set_level(self, index, level):
        pass


def test_wrong_acknowledged_mask_fails_the_burst(rig):
    board = _WrongAckBoard()
    result = capture_burst(board, rig.camera, burst_id=3, led_order=LEDS,
                           exposures_s=0.01, levels=1.0)
    assert not result.ok
    assert "switch" in result.reason and "LED 0" in result.reason
    assert board.off_calls == 1


@pytest.mark.parametrize(
    "options",
    [
        {"led_order": ()},
        {"led_order": (255,)},
        {"exposures_s": (0.01, 0.01)},
        {"exposures_s": 0.0},
        {"levels": 1.5},
        {"led_order": (1, 1), "levels": (0.5, 1.0)},
    ],
)
def test_bad_arguments_are_programming_errors(rig, options):
    with pytest.raises(ValueError):
        _burst(rig, **options)
    assert rig.emulator.history == []  # nothing was switched


def test_simulated_camera_checks_its_frames(rig):
    camera = SimulatedCamera(lambda lit: np.zeros((H, W), np.uint8), rig.emulator.lit_leds,
                             width=W, height=H, encoding="mono16")
    with camera:
        with pytest.raises(CameraError, match="dtype"):
            camera.grab(timeout_s=0.1)
    with pytest.raises(ValueError):
        SimulatedCamera(_render, rig.emulator.lit_leds, width=W, height=H, encoding="rgb8")
