"""Tests of fingerps_calib.calibration_camera: which intrinsics a calibration uses, and the
image size checks."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_calib import calibration_camera as cam
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics

K = np.array([[3000.0, 0.0, 329.0], [0.0, 3000.0, 246.0], [0.0, 0.0, 1.0]])
K_FILE = np.array([[6000.0, 0.0, 399.5], [0.0, 6000.0, 299.5], [0.0, 0.0, 1.0]])


def _driver(k: np.ndarray = K, d: list[float] | None = None, *, model: str = "plumb_bob",
            width: int = 640, height: int = 480) -> cam.DriverCameraInfo:
    return cam.DriverCameraInfo(k=np.asarray(k, float).ravel(),
                            d=np.zeros(5) if d is None else np.asarray(d, float),
                            distortion_model=model, width=width, height=height)


def _file() -> CameraIntrinsics:
    return CameraIntrinsics(width=800, height=600, camera_matrix=K_FILE,
                            distortion_model="plumb_bob", distortion=np.zeros(5),
                            camera_name="bench")


def test_camera_info_file_comes_before_the_driver():
    camera = cam.calibration_camera(_file(), _driver())
    assert (camera.width, camera.height, camera.source) == (800, 600,
                                                            "camera_info_file (bench)")
    np.testing.assert_array_equal(camera.matrix, K_FILE)
    assert camera.distortion is None
    assert cam.camera_image_size(_file(), _driver()) == (800, 600, "camera_info_file (bench)")


def test_the_driver_camera_info():
    d = [0.1, -0.2, 0.0, 0.0, 0.01]
    camera = cam.calibration_camera(None, _driver(d=d))
    np.testing.assert_array_equal(camera.matrix, K)
    np.testing.assert_array_equal(camera.distortion, d)
    assert camera.source == "the driver's camera_info" and camera.width == 640
    assert cam.camera_image_size(None, _driver()) == (640, 480, "the driver's camera_info")


def test_no_intrinsics_and_no_size():
    assert cam.calibration_camera(None, None) is None
    assert cam.calibration_camera(None, _driver(k=np.zeros(9))) is None
    assert cam.camera_image_size(None, None) is None
    assert cam.camera_image_size(None, _driver(width=0, height=0)) is None
    assert cam.camera_image_size(None, _driver(k=np.zeros(9))) == (640, 480,
                                                               "the driver's camera_info")


def test_bad_driver_intrinsics_are_refused():
    with pytest.raises(FingerpsCalibError, match=r"not finite \(K or D\); fix the driver's"):
        cam.calibration_camera(None, _driver(d=[np.nan, 0, 0, 0, 0]))
    with pytest.raises(FingerpsCalibError, match="'equidistant' is not supported"):
        cam.calibration_camera(None, _driver(d=[0.1, 0, 0, 0], model="equidistant"))
    assert cam.calibration_camera(None, _driver(d=[0.0] * 4, model="equidistant")) is not None


def test_size_checks():
    camera = cam.CalibrationCamera(K, None, 640, 480, "the driver's camera_info")
    cam.check_camera_size(np.zeros((2, 480, 640)), camera)
    cam.check_camera_size(np.zeros((2, 64, 64)), None)
    cam.check_camera_size(np.zeros((2, 64, 64)), cam.CalibrationCamera(K, None, 0, 0, "x"))
    with pytest.raises(FingerpsCalibError, match=r"^the images are 64x32 but the intrinsics "
                       r"\(the driver's camera_info\) are for 640x480"):
        cam.check_camera_size(np.zeros((2, 32, 64)), camera)
    cam.check_min_size(np.zeros((2, 64, 64)))
    with pytest.raises(FingerpsCalibError, match=r"^frames are 63x64 px; .* at least 64x64"):
        cam.check_min_size(np.zeros((2, 64, 63)))
    cam.check_frame_size(np.zeros((2, 480, 640)), (640, 480, "s"))
    cam.check_frame_size(np.zeros((2, 48, 64)), None)
    with pytest.raises(FingerpsCalibError, match=r"^the white-target frames are 64x48, the "
                       r"camera's images \(s\) 640x480"):
        cam.check_frame_size(np.zeros((2, 48, 64)), (640, 480, "s"))
