"""The HK solver's inputs checked (``photometric.hk_solver``): options, images, mask,
initial normals and albedo, usable measurements, lighting; each problem a
``FingerpsReconError`` that says what is wrong."""

from __future__ import annotations

import math

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.hk_model import SkinParams
from fingerps_recon.photometric.light_intensities import checked_intensities


def check_options(scale: float | None, iterations: int, tol: float) -> None:
    """FingerpsReconError unless scale is None or a finite number >= 0, iterations an
    integer >= 0 and tol a finite number >= 0."""
    if scale is not None and not (
        isinstance(scale, (int, float, np.integer, np.floating))
        and math.isfinite(scale) and scale >= 0
    ):
        raise FingerpsReconError(f"scale must be None (fit A) or a finite number >= 0, got {scale}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or (
        iterations < 0
    ):
        raise FingerpsReconError(f"iterations must be an integer >= 0, got {iterations!r}")
    if not (
        isinstance(tol, (int, float, np.integer, np.floating)) and math.isfinite(tol) and tol >= 0
    ):
        raise FingerpsReconError(f"tol must be a finite number >= 0, got {tol}")


def check_images(images: np.ndarray) -> np.ndarray:
    """The images (K, H, W) real, K >= 3, as an array (not copied); else FingerpsReconError."""
    imgs = np.asarray(images)
    if imgs.ndim != 3 or not (
        np.issubdtype(imgs.dtype, np.integer) or np.issubdtype(imgs.dtype, np.floating)
    ):
        raise FingerpsReconError(
            f"images must be a real (K, H, W) array, got shape {imgs.shape} dtype {imgs.dtype}"
        )
    if imgs.shape[0] < 3:
        raise FingerpsReconError(
            f"photometric stereo needs at least 3 lights, got {imgs.shape[0]}")
    return imgs


def checked_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != tuple(shape) or m.dtype != bool:
        raise FingerpsReconError(
            f"mask must be a bool array of shape (H, W) = {tuple(shape)}, got {m.shape} {m.dtype}"
        )
    return m


def check_burst(
    shape: tuple[int, int, int], mask: np.ndarray, init_normals: np.ndarray,
    init_albedo: np.ndarray, usable: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The burst's mask, initial normals and albedo and usable flags, checked against the
    images' (K, H, W) (FingerpsReconError on bad ones); nothing large is converted."""
    k, h, w = shape
    m = checked_mask(mask, (h, w))
    n_in = np.asarray(init_normals)
    if n_in.shape != (h, w, 3):
        raise FingerpsReconError(
            f"init_normals must have shape (H, W, 3) = ({h}, {w}, 3), got {n_in.shape}"
        )
    rho_in = np.asarray(init_albedo)
    if rho_in.shape != (h, w):
        raise FingerpsReconError(
            f"init_albedo must have shape (H, W) = ({h}, {w}), got {rho_in.shape}"
        )
    use_in = None
    if usable is not None:
        use_in = np.asarray(usable)
        if use_in.shape != (k, h, w) or use_in.dtype != bool:
            raise FingerpsReconError(
                f"usable must be a bool array of shape (K, H, W) = ({k}, {h}, {w}), got "
                f"{use_in.shape} {use_in.dtype}"
            )
    return m, n_in, rho_in, use_in


def check_lighting(
    lights: np.ndarray, shape: tuple[int, int], views: np.ndarray | tuple[float, float, float],
    intensities: np.ndarray | None, params: SkinParams,
) -> tuple[np.ndarray, bool, np.ndarray, np.ndarray]:
    """(lights, whether per pixel, views, intensities) checked for images of ``shape``
    (FingerpsReconError on bad ones): distant lights (K, 3) and a single view (3,)
    normalised (float64), intensities (K,) float64 or (K, H, W)."""
    h, w = shape
    lgt = np.asarray(lights)
    if lgt.ndim == 2 and lgt.shape[1] == 3:
        per_pixel = False
    elif lgt.ndim == 4 and lgt.shape[1:] == (h, w, 3):
        per_pixel = True
    else:
        raise FingerpsReconError(
            f"lights must have shape (K, 3) or (K, H, W, 3) = (K, {h}, {w}, 3) to match "
            f"images of {w} x {h} px, got {lgt.shape}"
        )
    k = lgt.shape[0]
    if k < 3:
        raise FingerpsReconError(f"photometric stereo needs at least 3 lights, got {k}")
    if not isinstance(params, SkinParams):
        raise FingerpsReconError(f"params must be a SkinParams, got {type(params).__name__}")
    vw = np.asarray(views)
    if vw.shape not in ((3,), (h, w, 3)):
        raise FingerpsReconError(
            f"views must have shape (3,) or (H, W, 3) = ({h}, {w}, 3), got {vw.shape}"
        )
    e = checked_intensities(intensities, shape=(k, h, w))
    if not per_pixel:
        lgt = unit_or_raise(lgt.astype(np.float64), "lights")
    if vw.ndim == 1:
        vw = unit_or_raise(vw.astype(np.float64), "views")
    return lgt, per_pixel, vw, e


def unit_or_raise(v: np.ndarray, name: str) -> np.ndarray:
    """``v`` (..., 3) normalised; FingerpsReconError if any vector is non-finite or zero."""
    if not np.all(np.isfinite(v)):
        raise FingerpsReconError(f"{name} contain non-finite values; check the calibration")
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise FingerpsReconError(f"{name} contain zero vectors; give unit directions")
    return v / norm
