"""Tests of fingerps_calib.intrinsics.checkerboard_calibration and the calibrate_camera command.

Synthetic views: a checkerboard texture is projected through a known camera with
cv2.warpPerspective (the homography K [r1 r2 t] of the board plane, rendered at 3x and
averaged down), then distorted with cv2.remap (each raw pixel shows the ideal image at its
undistorted position), plus noise.
"""

from __future__ import annotations

import stat
import subprocess

import cv2
import numpy as np
import pytest

from fingerps_calib.calibrate_camera_command import main
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import load_camera_info
from fingerps_calib.intrinsics.checkerboard_calibration import (
    board_points,
    calibrate_checkerboard,
    find_checkerboard,
)

W, H = 640, 480
K = np.array([[820.0, 0.0, 322.5], [0.0, 818.0, 236.0], [0.0, 0.0, 1.0]])
DISTORTION = np.array([-0.12, 0.05, 0.0005, -0.0008, 0.0])
PATTERN, SQUARE = (9, 6), 0.02


def _texture(px: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Board image (white margin of one square) and the map texture pixel -> board metres."""
    cols, rows = PATTERN[0] + 1, PATTERN[1] + 1
    texture = np.full(((rows + 2) * px, (cols + 2) * px), 255, np.uint8)
    for r in range(rows):
        for c in range(cols):
            if (r + c) % 2 == 0:
                texture[(r + 1) * px:(r + 2) * px, (c + 1) * px:(c + 2) * px] = 0
    a = SQUARE / px  # pixel centre x -> (x + 0.5) * a - 2 squares (first inner corner at 0)
    to_board = np.array([[a, 0, 0.5 * a - 2 * SQUARE], [0, a, 0.5 * a - 2 * SQUARE],
                         [0, 0, 1.0]])
    return texture, to_board


def _distortion_maps() -> tuple[np.ndarray, np.ndarray]:
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
    ideal = cv2.undistortPoints(np.stack([uu, vv], -1).reshape(-1, 1, 2), K, DISTORTION, P=K)
    ideal = ideal.reshape(H, W, 2)
    return ideal[..., 0], ideal[..., 1]


def _views(count: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    texture, to_board = _texture()
    map_u, map_v = _distortion_maps()
    ss = 3
    supersample = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
    views = []
    for _ in range(count):
        rvec = np.radians([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-20, 20)])
        rotation, _ = cv2.Rodrigues(rvec)
        t = -rotation @ np.array([0.08, 0.05, 0.0]) + np.array(
            [rng.uniform(-0.05, 0.05), rng.uniform(-0.03, 0.03), rng.uniform(0.38, 0.5)])
        homography = supersample @ K @ np.column_stack([rotation[:, 0], rotation[:, 1], t]) \
            @ to_board
        fine = cv2.warpPerspective(texture, homography, (W * ss, H * ss),
                                   flags=cv2.INTER_LINEAR, borderValue=128)
        ideal = cv2.resize(fine, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32)
        raw = cv2.remap(ideal, map_u, map_v, cv2.INTER_LINEAR, borderValue=128)
        raw = 40 + 0.7 * raw + rng.normal(0, 2.0, raw.shape)
        views.append(np.clip(np.round(raw), 0, 255).astype(np.uint8))
    return views


@pytest.fixture(scope="module")
def views() -> list[np.ndarray]:
    return _views(12, seed=0)


def test_intrinsics_and_distortion_are_recovered(views):
    result = calibrate_checkerboard(views, pattern=PATTERN, square_m=SQUARE,
                                    camera_name="synthetic")
    assert result.found.all()
    assert result.rms_px < 0.15
    assert np.all(result.view_rms_px < 0.2)
    k = result.intrinsics.camera_matrix
    np.testing.assert_allclose(k[[0, 1], [0, 1]], K[[0, 1], [0, 1]], rtol=3e-3)
    np.testing.assert_allclose(k[:2, 2], K[:2, 2], atol=2.0)
    # The distortion coefficients trade off against each other; what matters is how far the
    # distortion moves the points: over the area the boards covered, the estimate moves
    # them as the truth does, to a fraction of a pixel.
    corners = np.concatenate([find_checkerboard(v, pattern=PATTERN) for v in views])
    points = corners.reshape(-1, 1, 2).astype(np.float64)
    true_shift = cv2.undistortPoints(points, K, DISTORTION, P=K) - points
    got_shift = cv2.undistortPoints(points, k, result.intrinsics.distortion, P=k) - points
    error_px = np.linalg.norm((got_shift - true_shift).reshape(-1, 2), axis=1)
    assert np.abs(true_shift).max() > 2.0  # the distortion moves them by pixels
    assert error_px.max() < 0.5, error_px.max()
    assert np.sqrt(np.mean(error_px**2)) < 0.2
    assert result.intrinsics.distortion_model == "plumb_bob"
    assert (result.intrinsics.width, result.intrinsics.height) == (W, H)


def test_board_points_follow_opencv_order():
    points = board_points((3, 2), 0.01)
    np.testing.assert_allclose(points[:4], [[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0],
                                            [0, 0.01, 0]])


def test_failures_say_what_to_do(views):
    with pytest.raises(FingerpsCalibError, match=r"found in only 0 of 1.*inner corners"):
        calibrate_checkerboard(views[:1], pattern=(7, 7), square_m=SQUARE)
    with pytest.raises(FingerpsCalibError, match=r"at least 5 needed"):
        calibrate_checkerboard(views[:3], pattern=PATTERN, square_m=SQUARE)
    with pytest.raises(FingerpsCalibError, match="different sizes"):
        calibrate_checkerboard([views[0], views[1][:-2]], pattern=PATTERN, square_m=SQUARE)
    with pytest.raises(FingerpsCalibError, match="reprojects"):
        calibrate_checkerboard(views[:6], pattern=PATTERN, square_m=SQUARE, max_rms_px=0.01)


def test_the_command_writes_a_camera_info_file(views, tmp_path, capsys):
    folder = tmp_path / "boards"
    folder.mkdir()
    for index, view in enumerate(views[:8]):
        cv2.imwrite(str(folder / f"board_{index:02d}.png"), view)
    (folder / "notes.txt").write_text("not an image")
    out = tmp_path / "camera_info.yaml"
    code = main([str(folder), "--pattern", "9x6", "--square", "0.02", "--camera-name",
                 "kiosk_cam", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "board found in 8 of 8 images" in printed and f"wrote {out}" in printed
    info = load_camera_info(out)
    assert info.camera_name == "kiosk_cam" and (info.width, info.height) == (W, H)
    np.testing.assert_allclose(info.fx, K[0, 0], rtol=5e-3)
    # Failure: the wrong pattern -> exit 1 with the reason and the images listed.
    few = tmp_path / "few"
    few.mkdir()
    cv2.imwrite(str(few / "board.png"), views[0])
    assert main([str(few), "--pattern", "8x6", "--square", "0.02"]) == 1
    assert "found in only 0 of 1" in capsys.readouterr().err
    assert not (few / "camera_info.yaml").exists()
    # Bad input -> exit 2.
    assert main([str(tmp_path / "nowhere"), "--pattern", "9x6", "--square", "0.02"]) == 2
    with pytest.raises(SystemExit) as exit_info:
        main([str(folder), "--pattern", "nine", "--square", "0.02"])
    assert exit_info.value.code == 2


def test_the_command_writes_where_the_drivers_camera_info_url_looks(
        views, tmp_path, capsys, monkeypatch):
    folder = tmp_path / "boards"
    folder.mkdir()
    for index, view in enumerate(views[:8]):
        cv2.imwrite(str(folder / f"board_{index:02d}.png"), view)
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    # '' = the driver's default, ${ROS_HOME}/camera_info/${NAME}.yaml, owner-only
    assert main([str(folder), "--pattern", "9x6", "--square", "0.02", "--camera-name",
                 "kiosk_cam", "--camera-info-url", ""]) == 0
    out = tmp_path / "ros_home" / "camera_info" / "kiosk_cam.yaml"
    assert f"wrote {out}" in capsys.readouterr().out
    assert load_camera_info(out).camera_name == "kiosk_cam"
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    url = f"file://{tmp_path}/cal/${{NAME}}.yaml"
    assert main([str(folder), "--pattern", "9x6", "--square", "0.02", "--camera-name",
                 "c2", "--camera-info-url", url]) == 0
    assert load_camera_info(tmp_path / "cal" / "c2.yaml").camera_name == "c2"
    # A URL or a camera name the driver could not use: exit 2 before calibrating.
    assert main([str(folder), "--pattern", "9x6", "--square", "0.02",
                 "--camera-info-url", "http://x/c.yaml"]) == 2
    assert "not a calibration URL" in capsys.readouterr().err
    assert main([str(folder), "--pattern", "9x6", "--square", "0.02", "--camera-name",
                 "kiosk-cam", "--camera-info-url", ""]) == 2
    assert "letters, digits" in capsys.readouterr().err


def test_the_command_is_installed(installed):
    exe = installed("fingerps_calib", "calibrate_camera")
    done = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "--pattern" in done.stdout
