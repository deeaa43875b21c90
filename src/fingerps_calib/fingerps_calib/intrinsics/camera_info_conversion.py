"""Conversion between `CameraIntrinsics` and sensor_msgs/CameraInfo."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import CameraInfo

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics


def intrinsics_to_camera_info(intrinsics: CameraIntrinsics | None, *, width: int,
                              height: int) -> CameraInfo:
    """A CameraInfo of ``intrinsics``; with ``None``, an uncalibrated one (K = 0) of the size.

    ``width``/``height`` are the camera's; a calibration of another size is refused.
    """
    info = CameraInfo(width=int(width), height=int(height))
    if intrinsics is None:
        return info
    if (intrinsics.width, intrinsics.height) != (width, height):
        raise FingerpsCalibError(
            f"the calibration is for {intrinsics.width}x{intrinsics.height} images but the "
            f"camera delivers {width}x{height}")
    info.distortion_model = intrinsics.distortion_model
    info.d = [float(x) for x in intrinsics.distortion]
    info.k = [float(x) for x in intrinsics.camera_matrix.ravel()]
    info.r = [float(x) for x in intrinsics.rectification.ravel()]
    info.p = [float(x) for x in intrinsics.projection.ravel()]
    return info


def camera_info_to_intrinsics(info: CameraInfo, *, camera_name: str) -> CameraIntrinsics:
    """The intrinsics a CameraInfo carries (as ``camera_calibration`` sends them).

    Raises
    ------
    FingerpsCalibError
        No intrinsics (K = 0), numbers that are not finite, a distortion model whose
        coefficient count is wrong; the message names what.
    """
    k = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
    if not np.any(k):
        raise FingerpsCalibError("the CameraInfo carries no intrinsics (K is all zeros)")
    r = np.asarray(info.r, dtype=np.float64).reshape(3, 3)
    p = np.asarray(info.p, dtype=np.float64).reshape(3, 4)
    return CameraIntrinsics(
        width=int(info.width), height=int(info.height), camera_matrix=k,
        distortion_model=str(info.distortion_model),
        distortion=np.asarray(info.d, dtype=np.float64), camera_name=camera_name,
        rectification=r if np.any(r) else None, projection=p if np.any(p) else None)
