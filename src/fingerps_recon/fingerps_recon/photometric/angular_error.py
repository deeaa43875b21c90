"""Angular error between two normal maps, per pixel and summarised."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fingerps_recon.errors import FingerpsReconError


@dataclass(frozen=True)
class AngularErrorSummary:
    """Statistics of per-pixel angular errors, degrees.

    Attributes
    ----------
    mean, median, p95 : float
        Mean, median and 95th percentile of the finite errors (NaN if ``count`` is 0).
    count : int
        Number of pixels that entered the statistics.
    """

    mean: float
    median: float
    p95: float
    count: int


def angular_error_deg(
    estimated: np.ndarray, truth: np.ndarray, *, mask: np.ndarray | None = None
) -> np.ndarray:
    """Angle between estimated and true normals at each pixel.

    Parameters
    ----------
    estimated, truth : (..., 3) float
        Normals in the same frame, same shape. Only their directions count (they need not
        be unit length).
    mask : (...) bool, optional
        Pixels to evaluate; the others are NaN.

    Returns
    -------
    error : (...) float64
        Angle in degrees, in [0, 180]; NaN outside the mask and where either vector is zero
        or not finite.
    """
    est = np.asarray(estimated, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    if est.shape != tru.shape or est.ndim < 1 or est.shape[-1] != 3:
        raise FingerpsReconError(
            f"estimated {est.shape} and truth {tru.shape} must both have the shape (..., 3)"
        )
    n_est = np.linalg.norm(est, axis=-1)
    n_tru = np.linalg.norm(tru, axis=-1)
    ok = np.isfinite(n_est) & np.isfinite(n_tru) & (n_est > 0) & (n_tru > 0)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != est.shape[:-1] or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape {est.shape[:-1]}, got {m.shape} {m.dtype}"
            )
        ok &= m
    est = np.where(ok[..., None], est, 0.0)
    tru = np.where(ok[..., None], tru, 0.0)
    # atan2(|a x b|, a . b) is accurate at small and large angles alike (arccos is not).
    sin_part = np.linalg.norm(np.cross(est, tru), axis=-1)
    cos_part = np.einsum("...k,...k->...", est, tru)
    return np.where(ok, np.degrees(np.arctan2(sin_part, cos_part)), np.nan)


def summarize_angular_error(
    errors_deg: np.ndarray, *, mask: np.ndarray | None = None
) -> AngularErrorSummary:
    """Mean, median, 95th percentile and count of per-pixel angular errors.

    Parameters
    ----------
    errors_deg : (...) float
        Per-pixel errors in degrees, e.g. from :func:`angular_error_deg`; NaNs are skipped.
    mask : (...) bool, optional
        Pixels to include.

    Returns
    -------
    AngularErrorSummary
        Statistics of the finite errors inside the mask; NaN statistics and ``count`` 0 if
        there are none.
    """
    err = np.asarray(errors_deg, dtype=np.float64)
    sel = np.isfinite(err)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != err.shape or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape {err.shape}, got {m.shape} {m.dtype}"
            )
        sel &= m
    values = err[sel]
    if values.size == 0:
        return AngularErrorSummary(mean=np.nan, median=np.nan, p95=np.nan, count=0)
    return AngularErrorSummary(
        mean=float(values.mean()),
        median=float(np.median(values)),
        p95=float(np.percentile(values, 95)),
        count=int(values.size),
    )
