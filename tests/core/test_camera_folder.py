"""FolderCamera: replaying a DiLiGenT-layout folder, one image per LED, through the board."""

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from led_history import masks_lit_since, repeats_since

from fingerps_driver.board.board_emulator import BoardEmulator
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import Camera
from fingerps_driver.cameras.camera_folder import FolderCamera
from fingerps_driver.capture.burst import capture_burst
from fingerps_driver.errors import CameraError

H, W = 6, 8


def _folder(folder: Path, images, *, names=None, listed=None) -> Path:
    """Write ``images`` (grey, or colour given as BGR) and a filenames.txt listing them."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "img").mkdir(exist_ok=True)
    names = names or [f"img/{i:03d}.png" for i in range(len(images))]
    for name, image in zip(names, images, strict=True):
        assert cv2.imwrite(str(folder / name), image)
    (folder / "filenames.txt").write_text("\n".join(listed or names) + "\n\n")
    return folder


def _grey(count=7, dtype=np.uint8, step=10):
    return [np.full((H, W), step * (i + 1), dtype) for i in range(count)]


def test_each_led_sees_its_listed_image_through_the_serial_path(tmp_path):
    folder = _folder(tmp_path / "set", _grey())
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emulator, \
            LedBoard(emulator.port) as board, \
            FolderCamera(folder, lit_leds=emulator.lit_leds, led_count=7) as camera:
        assert isinstance(camera, Camera)
        assert (camera.width, camera.height, camera.encoding) == (W, H, "mono8")
        assert camera.names[2] == "img/002.png"
        start, resends = time.monotonic(), board.resends
        result = capture_burst(board, camera, burst_id=1, led_order=[6, 1, 3],
                               exposures_s=0.01, levels=1.0, with_dark=True)
        assert result.ok, result.reason
        assert [(f.led_index, int(f.image[0, 0])) for f in result.frames] == [
            (6, 70), (1, 20), (3, 40)]
        assert not result.dark.image.any()  # nothing lit: black
        assert masks_lit_since(emulator.history, start) == [64, 2, 8, 0]
        assert repeats_since(emulator.history, start) <= board.resends - resends


def test_acknowledged_mask_of_a_real_board_drives_the_replay(tmp_path):
    folder = _folder(tmp_path / "set", _grey())
    with BoardEmulator(7, link_path=str(tmp_path / "board")) as emulator, \
            LedBoard(emulator.port) as board:
        def acknowledged():
            mask = board.acknowledged_mask
            return [i for i in range(7) if mask >> i & 1]

        with FolderCamera(folder, lit_leds=acknowledged, led_count=7) as camera:
            board.set_leds(0b101)  # two LEDs: their light adds up
            assert int(camera.grab(timeout_s=0.1)[0, 0]) == 10 + 30


def test_sixteen_bit_colour_images_give_mono16_luma(tmp_path):
    images = []
    for i in range(3):
        bgr = np.zeros((H, W, 3), np.uint16)
        bgr[..., 2] = 10000 * (i + 1)  # red only
        images.append(bgr)
    folder = _folder(tmp_path / "deep", images)
    lit = [0]
    with FolderCamera(folder, lit_leds=lambda: lit, led_count=3) as camera:
        assert camera.encoding == "mono16"
        frame = camera.grab(timeout_s=0.1)
        assert frame.dtype == np.uint16 and abs(int(frame[0, 0]) - 2990) <= 1
        lit[:] = [0, 1, 2]
        assert abs(int(camera.grab(timeout_s=0.1)[0, 0]) - 17940) <= 2
        lit[:] = [7]
        with pytest.raises(CameraError, match=r"no image for LED\(s\) \[7\]"):
            camera.grab(timeout_s=0.1)


def test_sums_are_clipped_at_full_scale(tmp_path):
    folder = _folder(tmp_path / "bright", _grey(3, step=80))
    with FolderCamera(folder, lit_leds=lambda: [1, 2], led_count=3) as camera:
        assert int(camera.grab(timeout_s=0.1)[0, 0]) == 255


def test_the_folder_may_list_more_images_than_leds(tmp_path):
    folder = _folder(tmp_path / "many", _grey(10))
    with FolderCamera(folder, lit_leds=lambda: [6], led_count=7) as camera:
        assert len(camera.names) == 7 and int(camera.grab(timeout_s=0.1)[0, 0]) == 70


@pytest.mark.parametrize(("make", "words"), [
    (lambda d: d.mkdir(), "cannot read .*filenames.txt"),
    (lambda d: _folder(d, _grey(5)), "lists 5 images for 7 LEDs"),
    (lambda d: _folder(d, _grey(7), listed=[f"img/{i:03d}.png" for i in range(6)]
                       + ["img/missing.png"]), "cannot read .*missing.png.*LED 6"),
    (lambda d: _folder(d, [*_grey(6), np.zeros((H, W + 1), np.uint8)]),
     f"006.png \\(LED 6\\) is {W + 1}x{H} uint8, but the first image is {W}x{H}"),
    (lambda d: _folder(d, [*_grey(6), np.zeros((H, W), np.uint16)]), "uint16"),
])
def test_bad_folders_are_refused_at_open_naming_the_file(tmp_path, make, words):
    folder = tmp_path / "bad"
    make(folder)
    camera = FolderCamera(folder, lit_leds=lambda: [0], led_count=7)
    with pytest.raises(CameraError, match=words):
        camera.open()
    assert not camera.is_open
    with pytest.raises(CameraError, match="not open"):
        camera.grab(timeout_s=0.1)


def test_asked_size_and_encoding_must_match_the_images(tmp_path):
    folder = _folder(tmp_path / "set", _grey(3))
    with pytest.raises(CameraError, match=f"is {W}x{H}, not the 10x10 asked for"):
        FolderCamera(folder, lit_leds=lambda: [], led_count=3, width=10, height=10).open()
    with pytest.raises(CameraError, match="8-bit, not mono16"):
        FolderCamera(folder, lit_leds=lambda: [], led_count=3, encoding="mono16").open()
    with FolderCamera(folder, lit_leds=lambda: [], led_count=3, width=W, height=H,
                      encoding="mono8") as camera:
        assert camera.grab(timeout_s=0.1).shape == (H, W)


def test_bad_arguments_are_programming_errors(tmp_path):
    for kwargs in ({"led_count": 0}, {"encoding": "rgb8"}, {"width": 3}):
        with pytest.raises(ValueError):
            FolderCamera(tmp_path, **{"lit_leds": list, "led_count": 7, **kwargs})
