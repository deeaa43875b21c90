"""Heights and depths to 3D points in the camera's optical frame (pinhole model).

:func:`height_to_distance` turns the heights of the orthographic integration
(:func:`surface.integration.integrate_normals`) into distances along the optical axis;
:func:`depth_to_points` back-projects a depth map, x = (u - cx - s y_n) z / fx,
y = (v - cy) z / fy with y_n = (v - cy) / fy, in one compiled pass
(:mod:`surface.back_projection_kernel`).
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.mask_box import mask_bounding_box
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface.back_projection_kernel import back_project


def height_to_distance(height_m: np.ndarray, *, working_distance_m: float) -> np.ndarray:
    """Distance along the optical axis from a height map (PS z towards the camera).

    Parameters
    ----------
    height_m : (H, W) float
        Heights from :func:`surface.integration.integrate_normals` (metres, positive towards
        the camera).
    working_distance_m : float
        Distance along the optical axis of the height map's zero level, metres, > 0.

    Returns
    -------
    distance : (H, W) float32
        ``working_distance_m - height_m``; NaN stays NaN.
    """
    if not (np.isfinite(working_distance_m) and working_distance_m > 0):
        raise FingerpsReconError(
            f"working_distance_m must be a positive number, got {working_distance_m}"
        )
    return (working_distance_m - np.asarray(height_m, dtype=np.float64)).astype(np.float32)


def depth_to_points(
    depth_m: np.ndarray, mask: np.ndarray, *, camera_matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth map into 3D points in the camera optical frame (pinhole model).

    Parameters
    ----------
    depth_m : (H, W) float
        Distance along the optical axis (optical z, metres) of each pixel, see
        :func:`height_to_distance` and
        :func:`surface.integration.integrate_normals_perspective`.
    mask : (H, W) bool
        Pixels to back-project; pixels whose depth is not finite or not > 0 are left out.
    camera_matrix : (3, 3) float
        Intrinsics K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels.

    Returns
    -------
    points : (N, 3) float32
        x = (u - cx - s*y_n) z / fx, y = (v - cy) z / fy, z = depth (optical frame, metres),
        with y_n = (v - cy) / fy, for the selected pixels in raster order.
    index : (N,) int64
        Flat index (v * W + u) of each point's pixel, e.g. ``image.ravel()[index]`` gives the
        matching intensities.
    """
    depth = np.asarray(depth_m)
    m = np.asarray(mask)
    if depth.ndim != 2:
        raise FingerpsReconError(f"depth_m must have shape (H, W), got {depth.shape}")
    if m.shape != depth.shape or m.dtype != bool:
        raise FingerpsReconError(
            f"mask must be a bool array of the depth's shape {depth.shape}, got {m.shape} {m.dtype}"
        )
    k = checked_camera_matrix(camera_matrix)
    fx, s, cx = k[0]
    fy, cy = k[1, 1], k[1, 2]
    box = mask_bounding_box(m)
    if box is None:
        return np.empty((0, 3), dtype=np.float32), np.empty(0, dtype=np.int64)
    rows, cols = box
    y_row = ((np.arange(rows.start, rows.stop) - cy) / fy).astype(np.float32)  # y_n
    x_col = ((np.arange(cols.start, cols.stop) - cx) / fx).astype(np.float32)  # x_n, no skew
    most = int(np.count_nonzero(m[box]))
    points = np.empty((most, 3), dtype=np.float32)
    index = np.empty(most, dtype=np.int64)
    count = back_project(np.ascontiguousarray(depth, dtype=np.float32), np.ascontiguousarray(m),
                         rows.start, cols.start, y_row, x_col, np.float32(s / fx), points, index)
    return points[:count], index[:count]
