"""Correction of the lighting field (flat field, paper Eq. 11, NOTES §3.2).

The portion map p_k(i, j) = W_k(i, j) / max W_k of LED k, measured once on a white flat
target, describes how LED k's irradiance falls off across the field of view. Dividing each
later image under LED k by p_k makes its illumination uniform.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.errors import FingerpsReconError


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
    if imgs.shape != np.shape(portions):
        raise FingerpsReconError(
            f"images shape {imgs.shape} does not match portions shape {np.shape(portions)}; "
            "the flat field must be measured with the same LEDs and image size"
        )
    dtype = np.float64 if imgs.dtype == np.float64 else np.float32
    return imgs.astype(dtype) * flat_field_gain(portions, min_portion=min_portion, dtype=dtype)


def flat_field_gain(
    portions: np.ndarray, *, min_portion: float = 0.02, dtype: type = np.float32
) -> np.ndarray:
    """The factor of Eq. 11 that makes each LED's illumination uniform: 1 / p_k.

    Parameters
    ----------
    portions : (K, H, W) float
        Portion maps p_k in (0, 1] (Eq. 11).
    min_portion : float
        Portions below this are clipped to it, so dark corners of the flat field are not
        amplified without bound; in (0, 1].
    dtype : float32 or float64
        dtype of the result.

    Returns
    -------
    gain : (K, H, W) ``dtype``
        ``1 / max(portions, min_portion)``: multiply an image under LED k by ``gain[k]``.

    Raises
    ------
    FingerpsReconError
        If the portions are not (K, H, W) or not finite, or ``min_portion`` is out of range.
    """
    por = np.asarray(portions)
    if por.ndim != 3:
        raise FingerpsReconError(f"images and portions must be (K, H, W), got {por.shape}")
    if not 0 < min_portion <= 1:
        raise FingerpsReconError(f"min_portion must be in (0, 1], got {min_portion}")
    if not np.all(np.isfinite(por)):
        raise FingerpsReconError(
            "portions contain non-finite values; recompute the flat field (Eq. 11)"
        )
    return dtype(1.0) / np.maximum(por.astype(dtype, copy=False), dtype(min_portion))
