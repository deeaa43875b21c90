"""OpenCvCamera against OpenCV's real VideoCapture, and its V4L2 property path.

No camera device exists here, so the real API is exercised on what VideoCapture opens
without one: image sequences (``frame_%03d.png``; FFMPEG under CAP_ANY, OpenCV's own
reader under CAP_IMAGES, which keeps 16 bits) and an MJPG .avi written with VideoWriter.
What only a V4L2 device can show (that the driver accepts the FOURCC, exposure and gain
values) is checked as the exact property calls made, on a recording stand-in for
VideoCapture.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from fingerps_driver.board.board_emulator import BoardEmulator
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import Camera, ExposureControl, to_mono
from fingerps_driver.cameras.camera_opencv import OpenCvCamera, parse_device
from fingerps_driver.capture.burst import BurstStep, capture_burst
from fingerps_driver.errors import CameraError

H, W = 6, 8


def _sequence(folder: Path, images, name="frame") -> str:
    for i, image in enumerate(images):
        assert cv2.imwrite(str(folder / f"{name}_{i:03d}.png"), image)
    return str(folder / f"{name}_%03d.png")


def _grey_sequence(tmp_path, count=4):
    """Frames whose pixels are 10, 20, 30, ... so each frame says which one it is."""
    return _sequence(tmp_path, [np.full((H, W), 10 * (i + 1), np.uint8) for i in range(count)])


def test_it_is_a_camera_with_exposure_control(tmp_path):
    camera = OpenCvCamera(_grey_sequence(tmp_path), api=cv2.CAP_ANY)
    assert isinstance(camera, Camera) and isinstance(camera, ExposureControl)


def test_grey_image_sequence_gives_mono8_frames_in_order(tmp_path):
    with OpenCvCamera(_grey_sequence(tmp_path), api=cv2.CAP_ANY, discard_frames=0) as camera:
        # open() read frame 0 to learn the size
        assert (camera.width, camera.height, camera.encoding) == (W, H, "mono8")
        frames = [camera.grab(timeout_s=0.1) for _ in range(3)]
    assert [int(f[0, 0]) for f in frames] == [20, 30, 40]
    assert all(f.shape == (H, W) and f.dtype == np.uint8 for f in frames)
    assert camera.frames_grabbed == 3 and not camera.is_open


def test_discard_frames_drops_stale_frames_before_each_grab(tmp_path):
    with OpenCvCamera(_grey_sequence(tmp_path, 6), api=cv2.CAP_ANY, discard_frames=2) as camera:
        assert int(camera.grab(timeout_s=0.1)[0, 0]) == 40  # 10 at open, 20 and 30 dropped
        with pytest.raises(CameraError, match="no frame"):
            camera.grab(timeout_s=0.1)  # 50 and 60 dropped, then the sequence ends


def test_colour_frames_become_rec601_luma(tmp_path):
    bgr = np.zeros((H, W, 3), np.uint8)
    bgr[..., 0], bgr[..., 1], bgr[..., 2] = 200, 100, 50  # B, G, R
    with OpenCvCamera(_sequence(tmp_path, [bgr, bgr]), api=cv2.CAP_ANY,
                      discard_frames=0) as camera:
        grey = camera.grab(timeout_s=0.1)
    expected = round(0.299 * 50 + 0.587 * 100 + 0.114 * 200)
    assert grey.dtype == np.uint8 and np.all(np.abs(grey.astype(int) - expected) <= 1)


def test_mjpg_video_written_with_videowriter(tmp_path):
    path = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (32, 24), True)
    assert writer.isOpened()
    for level in (40, 120, 200):
        writer.write(np.full((24, 32, 3), level, np.uint8))
    writer.release()
    with OpenCvCamera(path, api=cv2.CAP_ANY, discard_frames=0) as camera:
        assert (camera.width, camera.height) == (32, 24)
        assert abs(float(camera.grab(timeout_s=0.1).mean()) - 120) < 4  # lossy JPEG
        assert abs(float(camera.grab(timeout_s=0.1).mean()) - 200) < 4
        with pytest.raises(CameraError, match=f"no frame from camera '{path}'"):
            camera.grab(timeout_s=0.1)
    # asking for a resolution the source does not give fails at open, naming both
    with pytest.raises(CameraError, match="32x24 frames, not the 64x48"):
        OpenCvCamera(path, api=cv2.CAP_ANY, width=64, height=48).open()


def test_mono16_keeps_sixteen_bits(tmp_path):
    images = [np.full((H, W), 1000 * (i + 1) + 7, np.uint16) for i in range(3)]
    images[1][2, 3] = 65535
    pattern = _sequence(tmp_path, images, "deep")
    with OpenCvCamera(pattern, api=cv2.CAP_IMAGES, pixel_format="mono16",
                      discard_frames=0) as camera:
        assert camera.encoding == "mono16"
        frame = camera.grab(timeout_s=0.1)
    assert frame.dtype == np.uint16 and np.array_equal(frame, images[1])
    # under CAP_IMAGES nothing of the V4L2 set-up applies: refused, listed, not fatal
    assert "fourcc=Y16 " in camera.refused_settings


def test_eight_bit_source_for_mono16_is_refused_at_open(tmp_path):
    with pytest.raises(CameraError, match="uint8 pixels, not uint16 for mono16; set the pixel "
                                          "format to mono8"):
        OpenCvCamera(_grey_sequence(tmp_path), api=cv2.CAP_IMAGES, pixel_format="mono16").open()


def test_settings_a_source_refuses_are_listed(tmp_path):
    camera = OpenCvCamera(_grey_sequence(tmp_path), api=cv2.CAP_ANY, fps=60.0,
                          exposure_s=0.004, gain=2.0, width=W, height=H)
    with camera:
        assert {"fps=60", "exposure=0.004 s", "gain=2"} <= set(camera.refused_settings)
        assert camera.grab(timeout_s=0.1).shape == (H, W)


def test_a_device_that_cannot_be_opened_is_named(tmp_path):
    missing = str(tmp_path / "none_%03d.png")
    with pytest.raises(CameraError, match=f"cannot open camera '{missing}'"):
        OpenCvCamera(missing, api=cv2.CAP_ANY).open()
    camera = OpenCvCamera(missing, api=cv2.CAP_ANY)
    with pytest.raises(CameraError, match="not open"):
        camera.grab(timeout_s=0.1)
    camera.close()
    camera.close()


def test_a_frame_of_the_wrong_size_mid_run_is_an_error(tmp_path):
    images = [np.full((H, W), 10, np.uint8), np.full((H, W), 20, np.uint8),
              np.full((H, W + 2), 30, np.uint8)]
    with OpenCvCamera(_sequence(tmp_path, images), api=cv2.CAP_IMAGES,
                      discard_frames=0) as camera:
        assert int(camera.grab(timeout_s=0.1)[0, 0]) == 20
        with pytest.raises(CameraError, match=f"10x{H} instead of {W}x{H}"):
            camera.grab(timeout_s=0.1)


def test_burst_with_a_real_videocapture_fails_cleanly_on_a_short_or_odd_source(tmp_path):
    images = [np.full((H, W), 10 * (i + 1), np.uint8) for i in range(9)]
    images[5] = np.full((H + 1, W), 99, np.uint8)  # LED 4's frame (frame 0 is read at open)
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emulator, \
            LedBoard(emulator.port) as board, \
            OpenCvCamera(_sequence(tmp_path, images), api=cv2.CAP_IMAGES,
                         discard_frames=0) as camera:
        result = capture_burst(board, camera, burst_id=1, led_order=range(7),
                               exposures_s=0.01, levels=1.0)
        assert not result.ok and result.failed_step is BurstStep.GRAB and result.camera_failed
        assert "LED 4" in result.reason and "CameraError" in result.reason
        assert emulator.lit_mask == 0
        result = capture_burst(board, camera, burst_id=2, led_order=range(7),
                               exposures_s=0.01, levels=1.0)
        assert not result.ok and "no frame" in result.reason  # the source ran dry


class _RecordingCapture:
    """Stands in for cv2.VideoCapture on a V4L2 device: records set(), serves frames."""

    def __init__(self, device, api, frames, accept=lambda prop: True):
        self.device, self.api = device, api
        self.frames = list(frames)
        self.calls: list[tuple[int, float]] = []
        self.accept = accept
        self.released = False

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop, value):
        self.calls.append((prop, value))
        return self.accept(prop)

    def grab(self):
        return bool(self.frames) and self.frames.pop(0) is not None

    def read(self):
        if not self.frames:
            return False, None
        frame = self.frames.pop(0)
        return frame is not None, frame

    def release(self):
        self.released = True


def test_v4l2_settings_are_the_right_properties_in_the_right_units():
    frames = [np.full((H, W), 500, np.uint16)] * 5
    made = []

    def factory(device, api):
        made.append(_RecordingCapture(device, api, frames))
        return made[-1]

    camera = OpenCvCamera(parse_device("/dev/video3"), width=W, height=H, fps=90,
                          exposure_s=0.004, gain=3.0, pixel_format="mono16",
                          capture_factory=factory)
    camera.open()
    capture = made[0]
    assert (capture.device, capture.api) == ("/dev/video3", cv2.CAP_V4L2)
    assert capture.calls == [
        (cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*"Y16 "))),
        (cv2.CAP_PROP_CONVERT_RGB, 0.0),
        (cv2.CAP_PROP_FRAME_WIDTH, float(W)),
        (cv2.CAP_PROP_FRAME_HEIGHT, float(H)),
        (cv2.CAP_PROP_FPS, 90.0),
        (cv2.CAP_PROP_BUFFERSIZE, 1.0),
        (cv2.CAP_PROP_AUTO_EXPOSURE, 1.0),  # V4L2_EXPOSURE_MANUAL
        (cv2.CAP_PROP_EXPOSURE, pytest.approx(40.0)),  # 100 us units
        (cv2.CAP_PROP_GAIN, 3.0),
    ]
    assert camera.refused_settings == []
    capture.calls.clear()
    camera.set_exposure(0.004)  # unchanged: nothing sent
    assert capture.calls == []
    camera.set_exposure(0.02)
    assert capture.calls == [(cv2.CAP_PROP_AUTO_EXPOSURE, 1.0),
                             (cv2.CAP_PROP_EXPOSURE, pytest.approx(200.0))]
    capture.calls.clear()
    frame = camera.grab(timeout_s=0.05)
    assert frame.dtype == np.uint16 and frame[0, 0] == 500
    assert capture.calls == [(cv2.CAP_PROP_READ_TIMEOUT_MSEC, 50.0)]
    camera.grab(timeout_s=0.05)  # same timeout: not sent again
    assert capture.calls == [(cv2.CAP_PROP_READ_TIMEOUT_MSEC, 50.0)]
    camera.close()
    assert capture.released
    assert parse_device("2") == 2 and parse_device(" /dev/video0 ") == "/dev/video0"


def test_v4l2_refusals_are_recorded_and_a_timeout_is_no_frame():
    capture = _RecordingCapture(0, cv2.CAP_V4L2, [np.zeros((H, W, 3), np.uint8), None],
                                accept=lambda prop: prop != cv2.CAP_PROP_EXPOSURE)
    camera = OpenCvCamera(0, exposure_s=0.01, discard_frames=0,
                          capture_factory=lambda device, api: capture)
    camera.open()
    assert camera.refused_settings == ["exposure=0.01 s"]
    assert camera.encoding == "mono8" and (camera.width, camera.height) == (W, H)
    with pytest.raises(CameraError, match=r"no frame from camera 0 within 0\.030 s"):
        camera.grab(timeout_s=0.03)


@pytest.mark.parametrize(("frame", "encoding", "words"), [
    (None, "mono8", "no frame"),
    (np.zeros((H, W), np.float32), "mono8", "float32 pixels"),
    (np.zeros((H, W, 2), np.uint8), "mono8", "shape"),
    (np.zeros((H, W), np.uint16), "mono8", "set the pixel format to mono16"),
])
def test_to_mono_refuses_what_is_not_a_mono_frame(frame, encoding, words):
    with pytest.raises(CameraError, match=words):
        to_mono(frame, encoding=encoding, source="camera x")


def test_to_mono_conversions():
    bgra = np.zeros((H, W, 4), np.uint16)
    bgra[..., 2] = 1000  # red
    grey = to_mono(bgra, encoding="mono16", source="x")
    assert grey.dtype == np.uint16 and abs(int(grey[0, 0]) - 299) <= 1
    single = np.arange(H * W, dtype=np.uint8).reshape(H, W, 1)
    out = to_mono(single, encoding="mono8", source="x")
    assert out.shape == (H, W) and out.flags.c_contiguous
    out[0, 0] = 255
    assert single[0, 0, 0] == 0  # a new array


def test_bad_arguments_are_programming_errors():
    for kwargs in ({"pixel_format": "rgb8"}, {"width": 10}, {"fps": -1.0},
                   {"exposure_s": -0.1}, {"fourcc": "MJPEG"}, {"discard_frames": -1}):
        with pytest.raises(ValueError):
            OpenCvCamera(0, **kwargs)


class _Board:
    """An LED board that acknowledges every switch (``burst.LedSwitch``)."""

    def set_leds(self, mask):
        return mask

    def all_off(self):
        pass

    def set_level(self, index, level):
        pass


def test_burst_sets_each_leds_exposure_before_switching_it_on():
    capture = _RecordingCapture("/dev/video0", cv2.CAP_V4L2, [np.zeros((H, W), np.uint8)] * 4)
    camera = OpenCvCamera("/dev/video0", exposure_s=0.01, discard_frames=0,
                          capture_factory=lambda device, api: capture)
    camera.open()
    capture.calls.clear()
    result = capture_burst(_Board(), camera, burst_id=1, led_order=[2, 0, 1],
                           exposures_s=[0.01, 0.02, 0.02], levels=1.0)
    assert result.ok, result.reason
    exposures = [value for prop, value in capture.calls if prop == cv2.CAP_PROP_EXPOSURE]
    assert exposures == [pytest.approx(200.0)]  # 0.01 s was set at open; 0.02 s once
    assert [f.exposure_s for f in result.frames] == [0.01, 0.02, 0.02]
