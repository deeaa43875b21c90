"""Tests of fingerps_calib.intrinsics.camera_info_yaml: round trip and error cases."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import (
    CameraIntrinsics,
    load_camera_info,
    save_camera_info,
)

# As camera_calibration writes it (ost.yaml), with numbers of a 659x493 camera.
ROS_TEXT = """\
image_width: 659
image_height: 493
camera_name: fingerps_camera
camera_matrix:
  rows: 3
  cols: 3
  data: [812.31, 0., 331.7, 0., 811.96, 244.2, 0., 0., 1.]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1123, 0.0456, 0.0003, -0.0002, 0.]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1., 0., 0., 0., 1., 0., 0., 0., 1.]
projection_matrix:
  rows: 3
  cols: 4
  data: [805.1, 0., 331.2, 0., 0., 806.3, 244.0, 0., 0., 0., 1., 0.]
"""


def _intrinsics() -> CameraIntrinsics:
    rng = np.random.default_rng(0)
    k = np.array([[812.3141592653589, 0.0, 331.7], [0.0, 811.9, 244.2], [0.0, 0.0, 1.0]])
    return CameraIntrinsics(
        width=659,
        height=493,
        camera_matrix=k,
        distortion_model="plumb_bob",
        distortion=rng.normal(scale=0.1, size=5),
        camera_name="fingerps camera",
        rectification=np.eye(3),
        projection=np.hstack([k + 0.1, np.zeros((3, 1))]),
    )


def test_reads_the_file_camera_calibration_writes(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_TEXT)
    cam = load_camera_info(path)
    assert (cam.width, cam.height, cam.camera_name) == (659, 493, "fingerps_camera")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (812.31, 811.96, 331.7, 244.2)
    assert cam.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(cam.distortion, [-0.1123, 0.0456, 0.0003, -0.0002, 0.0])
    np.testing.assert_array_equal(cam.rectification, np.eye(3))
    assert cam.projection.shape == (3, 4) and cam.projection[1, 2] == 244.0
    assert cam.camera_matrix.dtype == np.float64


def test_round_trip_is_exact(tmp_path):
    cam = _intrinsics()
    path = tmp_path / "camera.yaml"
    save_camera_info(path, cam)
    back = load_camera_info(path)
    assert back == cam
    np.testing.assert_array_equal(back.distortion, cam.distortion)
    # Saving what was read gives the same text (stable format).
    save_camera_info(tmp_path / "again.yaml", back)
    assert (tmp_path / "again.yaml").read_text() == path.read_text()
    assert not list(tmp_path.glob("*.tmp"))


def test_defaults_for_optional_keys(tmp_path):
    text = "\n".join(
        line
        for line in ROS_TEXT.splitlines()
        if not line.startswith("camera_name")
    )
    text = text.split("rectification_matrix:")[0]
    path = tmp_path / "short.yaml"
    path.write_text(text)
    cam = load_camera_info(path)
    assert cam.camera_name == "unknown"
    np.testing.assert_array_equal(cam.rectification, np.eye(3))
    np.testing.assert_array_equal(cam.projection[:, :3], cam.camera_matrix)
    np.testing.assert_array_equal(cam.projection[:, 3], 0.0)


def test_arrays_are_read_only_copies():
    k = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cam = CameraIntrinsics(640, 480, k, "plumb_bob", np.zeros(5))
    k[0, 0] = 1.0
    assert cam.fx == 800.0
    with pytest.raises(ValueError):
        cam.camera_matrix[0, 0] = 2.0


def test_missing_file_names_the_file(tmp_path):
    path = tmp_path / "nope.yaml"
    with pytest.raises(FingerpsCalibError, match=r"nope.yaml.*does not exist.*calibrat"):
        load_camera_info(path)


@pytest.mark.parametrize(
    "key", ["image_width", "image_height", "camera_matrix", "distortion_model",
            "distortion_coefficients"]
)
def test_missing_key_names_file_and_key(tmp_path, key):
    lines = ROS_TEXT.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(key + ":"))
    end = start + 1
    while end < len(lines) and lines[end].startswith("  "):
        end += 1
    path = tmp_path / "broken.yaml"
    path.write_text("\n".join(lines[:start] + lines[end:]) + "\n")
    with pytest.raises(FingerpsCalibError, match=rf"broken.yaml.*{key}.*recalibrate"):
        load_camera_info(path)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("rows: 3\n  cols: 4", "rows: 4\n  cols: 3", "projection_matrix.*4x3"),
        ("cols: 5\n  data: [-0.1123, 0.0456, 0.0003, -0.0002, 0.]",
         "cols: 4\n  data: [-0.1123, 0.0456, 0.0003, -0.0002]", "plumb_bob.*5 coefficients"),
        ("data: [812.31, 0., 331.7, 0., 811.96, 244.2, 0., 0., 1.]",
         "data: [812.31, 0., 331.7, 0., 811.96, 244.2, 0., 0.]", "camera_matrix.*8 numbers"),
        ("data: [812.31, 0., 331.7,", "data: [-812.31, 0., 331.7,", "fx, fy > 0"),
        ("image_width: 659", "image_width: wide", "image_width.*integer"),
        ("data: [1., 0., 0., 0., 1.,", "data: [1., 0., .nan, 0., 1.,",
         "rectification_matrix.*non-finite"),
    ],
)
def test_bad_contents_are_named(tmp_path, old, new, message):
    assert old in ROS_TEXT
    path = tmp_path / "bad.yaml"
    path.write_text(ROS_TEXT.replace(old, new, 1))
    with pytest.raises(FingerpsCalibError, match=rf"bad.yaml.*{message}"):
        load_camera_info(path)


def test_not_yaml_or_not_a_mapping(tmp_path):
    path = tmp_path / "junk.yaml"
    path.write_text("image_width: [unclosed\n")
    with pytest.raises(FingerpsCalibError, match=r"junk.yaml.*not valid YAML"):
        load_camera_info(path)
    path.write_text("- 1\n- 2\n")
    with pytest.raises(FingerpsCalibError, match=r"junk.yaml.*mapping"):
        load_camera_info(path)


def test_save_into_missing_directory_says_so(tmp_path):
    with pytest.raises(FingerpsCalibError, match=r"cannot write.*directory exists"):
        save_camera_info(tmp_path / "no" / "such" / "dir.yaml", _intrinsics())
