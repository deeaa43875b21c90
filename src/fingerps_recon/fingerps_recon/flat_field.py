"""Correction of the lighting field (flat field, paper Eq. 11, NOTES §3.2).

The portion map p_k(i, j) = W_k(i, j) / max W_k of LED k, measured once on a white flat
target, describes how LED k's irradiance falls off across the field of view. Dividing each
later image under LED k by p_k makes its illumination uniform.
"""

from __future__ import annotations

import numpy as np

from .errors import FingerpsReconError


def apply_flat_field(
    images: np.ndarray, portions: np.ndarray, *, min_portion: float = 0.02
) -> np.ndarray:
    """Divide each image by its LED's portion map (paper Eq. 11).

    Parameters
    ----------
    images : (K, H, W) float or int
        One image per LED.
    portions : (K, H, W) float
        Portion maps p_k in (0, 1] (Eq. 11), same shape as ``images``.
    min_portion : float
        Portions below this are clipped to it, so dark corners of the flat field are not
        amplified without bound; in (0, 1].

    Returns
    -------
    corrected : (K, H, W) float
        ``images / max(portions, min_portion)``; float64 if ``images`` is float64, else
        float32.

    Raises
    ------
    FingerpsReconError
        If the shapes differ or are not (K, H, W), ``min_portion`` is out of range, or the
        portions are not finite.
    """
    imgs = np.asarray(images)
    por = np.asarray(portions)
    if imgs.shape != por.shape:
        raise FingerpsReconError(
            f"images shape {imgs.shape} does not match portions shape {por.shape}; the flat "
            "field must be measured with the same LEDs and image size"
        )
    if imgs.ndim != 3:
        raise FingerpsReconError(f"images and portions must be (K, H, W), got {imgs.shape}")
    if not 0 < min_portion <= 1:
        raise FingerpsReconError(f"min_portion must be in (0, 1], got {min_portion}")
    if not np.all(np.isfinite(por)):
        raise FingerpsReconError(
            "portions contain non-finite values; recompute the flat field (Eq. 11)"
        )
    dtype = np.float64 if imgs.dtype == np.float64 else np.float32
    divisor = np.maximum(por.astype(dtype, copy=False), dtype(min_portion))
    return imgs.astype(dtype) / divisor
