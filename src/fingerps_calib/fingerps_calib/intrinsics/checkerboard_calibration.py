"""Camera intrinsics from images of a checkerboard (OpenCV), for cameras without a camera_info.

`calibrate_checkerboard`: the inner corners of the board are found in each image
(``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix``; where that fails, the slower
``cv2.findChessboardCornersSB``), and ``cv2.calibrateCamera`` fits K and the plumb_bob distortion
(k1, k2, p1, p2, k3) to all views. The result is a `CameraIntrinsics`, which
`intrinsics.camera_info_yaml.save_camera_info` writes in the format camera_calibration
writes and camera_info_manager reads.

Good practice (as for camera_calibration): 10-20 views, the board tilted up to ~45 deg in
various directions and covering the corners of the image; the board flat; no motion blur.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics


@dataclass(frozen=True, eq=False)
class CheckerboardCalibration:
    """Result of `calibrate_checkerboard`.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    rms_px : float
        RMS reprojection error over all corners of all used views, pixels.
    view_rms_px : (N,) float64
        RMS reprojection error of each image; NaN where the board was not found.
    found : (N,) bool
        Whether the board was found in each image.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: np.ndarray
    found: np.ndarray


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """(C*R, 3) float32 corner positions on the board plane z = 0, metres, in the order
    OpenCV reports them (row by row, ``pattern`` = (columns, rows) of inner corners)."""
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)


def find_checkerboard(image: np.ndarray, *, pattern: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners of a checkerboard, or None if it is not (wholly) seen.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, uint8 or uint16 (or float in [0, 1])
    pattern : (int, int)
        Inner corners per row and per column, e.g. (9, 6) for a 10 x 7 squares board.

    Returns
    -------
    (C*R, 2) float32 or None
    """
    gray = _gray8(image)
    found, corners = cv2.findChessboardCorners(
        gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found:
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
    else:  # the sector-based detector copes with blur and uneven light, ~30x slower
        found, corners = cv2.findChessboardCornersSB(
            gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        if not found:
            return None
    return corners.reshape(-1, 2).astype(np.float32)


def calibrate_checkerboard(
    images: Sequence[np.ndarray],
    *,
    pattern: tuple[int, int],
    square_m: float,
    camera_name: str = "camera",
    min_views: int = 5,
    max_rms_px: float = 1.0,
) -> CheckerboardCalibration:
    """Intrinsics K and plumb_bob distortion from N images of a checkerboard.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) arrays, all of one size
    pattern : (int, int)
        Inner corners per row and per column.
    square_m : float
        Side of a square, metres (sets the units of the board poses only; K is in pixels).
    camera_name : str
        Written into the intrinsics.
    min_views : int
        Fewest images in which the board must be found.
    max_rms_px : float
        Largest acceptable rms reprojection error.

    Returns
    -------
    CheckerboardCalibration

    Raises
    ------
    FingerpsCalibError
        Images of different sizes, the board found in fewer than ``min_views`` images, or
        a reprojection error above ``max_rms_px``; the message says which images and what
        to do.
    """
    if len(pattern) != 2 or min(pattern) < 2:
        raise FingerpsCalibError(
            f"pattern {pattern} must be (columns, rows) of inner corners, each >= 2")
    if not square_m > 0:
        raise FingerpsCalibError(f"square size {square_m} m must be positive")
    if not images:
        raise FingerpsCalibError("no images: give 10-20 views of the checkerboard")
    shapes = {np.shape(im)[:2] for im in images}
    if len(shapes) != 1:
        raise FingerpsCalibError(
            f"the images have different sizes {sorted(shapes)}; use one camera and one "
            "resolution")
    (h, w), = shapes
    found_corners = [find_checkerboard(im, pattern=pattern) for im in images]
    found = np.array([c is not None for c in found_corners])
    if found.sum() < min_views:
        missing = ", ".join(str(i) for i in np.flatnonzero(~found))
        raise FingerpsCalibError(
            f"the {pattern[0]}x{pattern[1]} inner-corner checkerboard was found in only "
            f"{int(found.sum())} of {len(images)} images (at least {min_views} needed; not "
            f"found in images {missing}): check the pattern size (inner corners, not "
            "squares), that the whole board is in view, sharp and evenly lit")
    objects = board_points(pattern, square_m)
    object_points = [objects for c in found_corners if c is not None]
    image_points = [c.reshape(-1, 1, 2) for c in found_corners if c is not None]
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(
        object_points, image_points, (w, h), None, None)
    view_rms = np.full(len(images), np.nan)
    for index, rvec, tvec, corners in zip(np.flatnonzero(found), rvecs, tvecs, image_points,
                                          strict=True):
        projected, _ = cv2.projectPoints(objects, rvec, tvec, k, dist)
        view_rms[index] = float(np.sqrt(np.mean(np.sum(
            (projected.reshape(-1, 2) - corners.reshape(-1, 2)) ** 2, axis=1))))
    if not rms <= max_rms_px:
        worst = int(np.nanargmax(view_rms))
        raise FingerpsCalibError(
            f"the calibration reprojects the corners to {rms:.2f} px rms (at most "
            f"{max_rms_px} px; worst image {worst}: {view_rms[worst]:.2f} px): remove "
            "blurred views or views of a bent board, and check the square size")
    k[np.abs(k) < 1e-300] = 0.0
    intrinsics = CameraIntrinsics(
        width=w, height=h, camera_matrix=k, distortion_model="plumb_bob",
        distortion=np.ravel(dist)[:5], camera_name=camera_name,
        projection=np.hstack([k, np.zeros((3, 1))]))
    return CheckerboardCalibration(intrinsics=intrinsics, rms_px=float(rms),
                                   view_rms_px=view_rms, found=found)


def _gray8(image: np.ndarray) -> np.ndarray:
    """The image as (H, W) uint8 (colour averaged; 16-bit and float scaled)."""
    a = np.asarray(image)
    if a.ndim == 3:
        a = a.astype(np.float64).mean(axis=2)
    if a.ndim != 2:
        raise FingerpsCalibError(f"image of shape {np.shape(image)}: expected (H, W) or (H, W, 3)")
    if a.dtype == np.uint8:
        return a
    a = a.astype(np.float64)
    top = float(a.max()) if a.size else 1.0
    scale = 255.0 / top if top > 0 else 1.0
    return np.clip(a * scale, 0, 255).astype(np.uint8)
