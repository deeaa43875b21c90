"""Lambertian photometric stereo (paper Eq. 3, NOTES §2): forward shading and the solver.

Per pixel, I_k = e_k * rho * max(0, l_k . n) for lights k with unit directions l_k (PS frame,
from the surface towards the light) and relative intensities e_k. With the rows of L scaled
by e_k, b = rho * n = (L^T L)^-1 L^T I over the lights that are usable at that pixel (not
in shadow, not saturated); rho = |b|, n = b / |b|.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import FingerpsReconError

# Smallest singular value of the used (scaled) light matrix, relative to its largest, below
# which a pixel's light subset is treated as degenerate (e.g. coplanar light directions).
_MIN_RELATIVE_SINGULAR_VALUE = 1e-6


def lambertian_shading(
    normals: np.ndarray, lights: np.ndarray, *, rho: np.ndarray | float
) -> np.ndarray:
    """Lambertian image formation rho * max(0, n . l) (paper Eq. 3).

    Parameters
    ----------
    normals : (..., 3) float
        Unit surface normals, PS frame.
    lights : (..., 3) float
        Unit directions from the surface towards the light, PS frame; broadcasts with
        ``normals`` (e.g. normals (H, W, 3), lights (K, 1, 1, 3) -> (K, H, W)).
    rho : (...) float or float
        Albedo (times light intensity), broadcasting with the result.

    Returns
    -------
    intensity : (...) float
        float32 if all array inputs are float32, else float64.
    """
    n = np.asarray(normals)
    lgt = np.asarray(lights)
    for name, arr in (("normals", n), ("lights", lgt)):
        if arr.ndim < 1 or arr.shape[-1] != 3:
            raise FingerpsReconError(f"{name} must have shape (..., 3), got {arr.shape}")
    try:
        np.broadcast_shapes(n.shape, lgt.shape)
    except ValueError:
        raise FingerpsReconError(
            f"normals {n.shape} and lights {lgt.shape} do not broadcast together; add "
            "singleton axes, e.g. lights[:, None, None, :]"
        ) from None
    rho_in = rho if isinstance(rho, (int, float)) else np.asarray(rho)
    dtype = np.result_type(n, lgt, rho_in, np.float32)
    cos = np.einsum("...k,...k->...", n.astype(dtype, copy=False), lgt.astype(dtype, copy=False))
    return (np.asarray(rho_in, dtype=dtype) * np.maximum(cos, 0)).astype(dtype, copy=False)


@dataclass(frozen=True)
class LambertianResult:
    """Result of :func:`solve_lambertian`.

    Attributes
    ----------
    normals : (H, W, 3) float32
        Unit normals in the PS frame; zeros where not ``valid``.
    albedo : (H, W) float32
        rho = |b| in image units per unit relative intensity; zero where not ``valid``.
    valid : (H, W) bool
        Pixels with at least 3 usable, non-degenerate lights and a non-zero solution.
    used_lights : (H, W) uint8
        Number of lights used at each pixel (0 outside the mask).
    """

    normals: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    used_lights: np.ndarray


def solve_lambertian(
    images: np.ndarray,
    lights: np.ndarray,
    *,
    intensities: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    shadow_level: float = 0.0,
    saturation_level: float | None = None,
) -> LambertianResult:
    """Least-squares Lambertian photometric stereo with per-pixel light selection (Eq. 3).

    At each pixel the lights whose value is <= ``shadow_level`` (attached or cast shadow)
    or >= ``saturation_level`` (clipped), or not finite, are left out; the rest give
    b = rho n = pinv(L_used) I_used. Pixels are grouped by their pattern of usable lights
    (at most 2^K groups, in practice a few dozen) and each group is solved with one
    pseudo-inverse. Pixels with fewer than 3 usable lights, or whose usable lights are
    degenerate (coplanar directions), are marked invalid rather than guessed. The sign of
    n_z is not forced.

    Parameters
    ----------
    images : (K, H, W) float or int
        One image per light, any linear scale (flat-field corrected, dark-subtracted).
    lights : (K, 3) float
        Unit directions from the surface towards each light, PS frame.
    intensities : (K,) float, optional
        Relative light intensities e_k > 0, scaling the rows of L; default all ones.
    mask : (H, W) bool, optional
        Pixels to solve; the rest are invalid. Default: all.
    shadow_level : float
        Values <= this are treated as shadowed, in image units. Default 0.
    saturation_level : float, optional
        Values >= this are treated as saturated. Default: no saturation test.

    Returns
    -------
    LambertianResult

    Raises
    ------
    FingerpsReconError
        On inconsistent shapes, fewer than 3 lights, or non-positive intensities.
    """
    imgs = np.asarray(images)
    lgt = np.asarray(lights, dtype=np.float64)
    if imgs.ndim != 3:
        raise FingerpsReconError(f"images must have shape (K, H, W), got {imgs.shape}")
    k, h, w = imgs.shape
    if lgt.shape != (k, 3):
        raise FingerpsReconError(
            f"lights must have shape (K, 3) = ({k}, 3) to match images {imgs.shape}, "
            f"got {lgt.shape}"
        )
    if k < 3:
        raise FingerpsReconError(f"photometric stereo needs at least 3 lights, got {k}")
    if k > 62:
        raise FingerpsReconError(f"at most 62 lights are supported, got {k}")
    if not np.all(np.isfinite(lgt)):
        raise FingerpsReconError("lights contain non-finite values; check the calibration")
    if intensities is None:
        e = np.ones(k)
    else:
        e = np.asarray(intensities, dtype=np.float64)
        if e.shape != (k,):
            raise FingerpsReconError(f"intensities must have shape (K,) = ({k},), got {e.shape}")
        if not np.all(np.isfinite(e) & (e > 0)):
            raise FingerpsReconError(f"intensities must be finite and > 0, got {e}")
    if mask is None:
        m = np.ones((h, w), dtype=bool)
    else:
        m = np.asarray(mask)
        if m.shape != (h, w) or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape (H, W) = ({h}, {w}), got {m.shape} {m.dtype}"
            )
    scaled = lgt * e[:, None]

    pix = np.flatnonzero(m)
    values = imgs.reshape(k, h * w)[:, pix].astype(np.float64)  # (K, N), a copy
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(values) & (values > shadow_level)
        if saturation_level is not None:
            usable &= values < saturation_level
    values[~usable] = 0.0  # multiplied by zero weights below; no NaN may remain
    bits = np.left_shift(np.int64(1), np.arange(k, dtype=np.int64))
    codes = bits @ usable  # (N,) light-pattern code per pixel
    counts = usable.sum(axis=0)

    # Sort the pixels by pattern so that each group is a contiguous slice; each group's
    # pseudo-inverse is expanded to (3, K) with zero columns for the unused lights.
    order = np.argsort(codes, kind="stable")
    sorted_values = values[:, order]
    sorted_b = np.zeros((3, pix.size))
    sorted_solved = np.zeros(pix.size, dtype=bool)
    group_codes, starts = np.unique(codes[order], return_index=True)
    ends = np.append(starts[1:], order.size)
    for code, start, end in zip(group_codes, starts, ends, strict=True):
        sel = (int(code) & bits) != 0
        if np.count_nonzero(sel) < 3:
            continue
        l_used = scaled[sel]
        sv = np.linalg.svd(l_used, compute_uv=False)
        if sv[-1] <= _MIN_RELATIVE_SINGULAR_VALUE * sv[0]:
            continue
        pinv = np.zeros((3, k))
        pinv[:, sel] = np.linalg.pinv(l_used)
        sorted_b[:, start:end] = pinv @ sorted_values[:, start:end]
        sorted_solved[start:end] = True
    b = np.empty_like(sorted_b)
    b[:, order] = sorted_b
    solved = np.empty_like(sorted_solved)
    solved[order] = sorted_solved

    rho = np.linalg.norm(b, axis=0)
    ok = solved & np.isfinite(rho) & (rho > 0)
    normals = np.zeros((h * w, 3), dtype=np.float32)
    albedo = np.zeros(h * w, dtype=np.float32)
    valid = np.zeros(h * w, dtype=bool)
    used = np.zeros(h * w, dtype=np.uint8)
    normals[pix[ok]] = (b[:, ok] / rho[ok]).T
    albedo[pix[ok]] = rho[ok]
    valid[pix[ok]] = True
    used[pix] = counts
    return LambertianResult(
        normals=normals.reshape(h, w, 3),
        albedo=albedo.reshape(h, w),
        valid=valid.reshape(h, w),
        used_lights=used.reshape(h, w),
    )
