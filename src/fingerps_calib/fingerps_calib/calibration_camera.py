"""The camera a calibration is made with: its intrinsics and the size of its images.

The intrinsics come from ``camera_info_file`` when calib_node has one, else from the
driver's camera_info (given here as `DriverCameraInfo`, plain values of a
sensor_msgs/CameraInfo). The checks refuse frames too small to calibrate from and frames
of another size than the camera's, with a message saying what to send instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import MIN_IMAGE_SIDE_PX
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics

DRIVER_SOURCE = "the driver's camera_info"


@dataclass(frozen=True, eq=False)
class DriverCameraInfo:
    """What the driver's sensor_msgs/CameraInfo says, as plain values.

    Attributes
    ----------
    k : (9,) float64
        K row by row (all zeros: the camera is not calibrated).
    d : (n,) float64
        Distortion coefficients.
    distortion_model : str
    width, height : int
        Image size in pixels (0: unknown).
    frame_id : str
        The header's frame id ('' when unset).
    """

    k: np.ndarray
    d: np.ndarray
    distortion_model: str
    width: int
    height: int
    frame_id: str = ""


@dataclass(frozen=True, eq=False)
class CalibrationCamera:
    """The intrinsics a calibration uses and where they came from.

    Attributes
    ----------
    matrix : (3, 3) float64
        K, pixels.
    distortion : (n,) float64 or None
        None when there is no distortion.
    width, height : int
        Image size of the intrinsics (0: unknown).
    source : str
        Where they came from, for messages.
    """

    matrix: np.ndarray
    distortion: np.ndarray | None
    width: int
    height: int
    source: str


def file_source(intrinsics: CameraIntrinsics) -> str:
    """How messages name intrinsics read from ``camera_info_file``."""
    return f"camera_info_file ({intrinsics.camera_name})"


def calibration_camera(file_camera: CameraIntrinsics | None,
                       info: DriverCameraInfo | None) -> CalibrationCamera | None:
    """The intrinsics to use: ``file_camera`` if set, else the driver's camera_info.

    Returns None when neither gives intrinsics (no camera_info, or K = 0).

    Raises
    ------
    FingerpsCalibError
        The driver's K or D are not finite, or a distortion model the light calibration
        does not handle.
    """
    if file_camera is not None:
        c = file_camera
        return CalibrationCamera(np.array(c.camera_matrix),
                                 _distortion(c.distortion_model, c.distortion),
                                 c.width, c.height, file_source(c))
    if info is None or info.k[0] <= 0:
        return None
    if not np.all(np.isfinite(info.k)) or not np.all(np.isfinite(info.d)):
        raise FingerpsCalibError(
            "the driver's camera_info has intrinsics that are not finite (K or D); fix "
            "the driver's camera_info_file or set calib_node's camera_info_file")
    return CalibrationCamera(np.reshape(np.asarray(info.k, dtype=np.float64), (3, 3)),
                             _distortion(info.distortion_model,
                                         np.asarray(info.d, dtype=float)),
                             int(info.width), int(info.height), DRIVER_SOURCE)


def camera_image_size(file_camera: CameraIntrinsics | None,
                      info: DriverCameraInfo | None) -> tuple[int, int, str] | None:
    """(width, height, source) of the camera's images, when known."""
    if file_camera is not None and file_camera.width > 0:
        return file_camera.width, file_camera.height, file_source(file_camera)
    if info is not None and info.width > 0 and info.height > 0:
        return int(info.width), int(info.height), DRIVER_SOURCE
    return None


def check_min_size(images: np.ndarray) -> None:
    """Refuse frames smaller than `MIN_IMAGE_SIDE_PX` on a side; ``images`` (K, H, W)."""
    h, w = images.shape[1:]
    if min(h, w) < MIN_IMAGE_SIDE_PX:
        raise FingerpsCalibError(
            f"frames are {w}x{h} px; a calibration needs whole camera frames of at least "
            f"{MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX} (the flat field is fitted to 64 "
            "blocks across the short side, the sphere's silhouette needs pixels): send "
            "full frames, or no frames to capture a burst through the driver")


def check_camera_size(images: np.ndarray, camera: CalibrationCamera | None) -> None:
    """Refuse ``images`` (K, H, W) of another size than the intrinsics' (when known)."""
    if camera is None or camera.width <= 0:
        return
    h, w = images.shape[1:]
    if (w, h) != (camera.width, camera.height):
        raise FingerpsCalibError(
            f"the images are {w}x{h} but the intrinsics ({camera.source}) are for "
            f"{camera.width}x{camera.height}: use the camera the intrinsics belong to, or "
            "the intrinsics of this camera")


def check_frame_size(images: np.ndarray, size: tuple[int, int, str] | None) -> None:
    """Refuse white-target ``images`` (K, H, W) of another size than the camera's."""
    if size is not None and (images.shape[2], images.shape[1]) != size[:2]:
        raise FingerpsCalibError(
            f"the white-target frames are {images.shape[2]}x{images.shape[1]}, the "
            f"camera's images ({size[2]}) {size[0]}x{size[1]}: send whole frames of "
            "this camera, or no frames to capture a burst through the driver")


def _distortion(model: str, coefficients: np.ndarray) -> np.ndarray | None:
    coefficients = np.asarray(coefficients, dtype=np.float64).ravel()
    if not np.any(coefficients):
        return None
    if model in ("plumb_bob", "rational_polynomial"):
        return coefficients
    raise FingerpsCalibError(
        f"distortion model {model!r} is not supported by the light calibration; give "
        "rectified images with plumb_bob intrinsics")
