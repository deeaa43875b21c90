"""Ridge enhancement of a normal map (paper Eq. 12, NOTES §4).

n' = n + k (n - normalize(sum_{j in w x w} n_j)), then renormalised: each normal is pushed
away from the mean direction of its w x w neighbourhood, which amplifies the angle between
neighbouring normals and so the visual contrast of the ridges. Paper: w = 7, k = 2.5.
It is for display, applied after the normals are estimated, not for integration.
"""

from __future__ import annotations

import cv2
import numpy as np

from .errors import FingerpsReconError


def enhance_ridges(
    normals: np.ndarray,
    *,
    w: int = 7,
    k: float = 2.5,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Amplify the differences between neighbouring normals (paper Eq. 12).

    The patch sum counts only neighbours inside the image and the mask (normalised
    convolution: outside neighbours are zero, and the sum is normalised to a direction, so
    no division by the count is needed).

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals (PS frame); zero vectors mark pixels without a normal.
    w : int
        Side of the square patch, odd, >= 3.
    k : float
        Gain, >= 0; k = 0 returns the (renormalised) input.
    mask : (H, W) bool, optional
        Pixels to enhance and to use as neighbours; outside it the output is zero.

    Returns
    -------
    enhanced : (H, W, 3) float
        Unit normals (zero where the input is zero or outside the mask); float64 if
        ``normals`` is float64, else float32. The input is not modified.
    """
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise FingerpsReconError(f"normals must have shape (H, W, 3), got {n.shape}")
    if isinstance(w, bool) or not isinstance(w, (int, np.integer)) or w < 3 or w % 2 == 0:
        raise FingerpsReconError(f"w must be an odd integer >= 3, got {w!r}")
    if not (np.isfinite(k) and k >= 0):
        raise FingerpsReconError(f"k must be a finite number >= 0, got {k!r}")
    dtype = np.float64 if n.dtype == np.float64 else np.float32
    src = n.astype(dtype)  # always a copy
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != n.shape[:2] or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape {n.shape[:2]}, got {m.shape} {m.dtype}"
            )
        src[~m] = 0
    src[~np.all(np.isfinite(src), axis=2)] = 0

    patch_sum = cv2.boxFilter(
        src, -1, (int(w), int(w)), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    mean_dir = _normalize(patch_sum)
    has_mean = np.any(mean_dir != 0, axis=2, keepdims=True)
    # Where no neighbour has a normal, leave the normal unchanged.
    mean_dir = np.where(has_mean, mean_dir, src)
    enhanced = src + dtype(k) * (src - mean_dir)
    enhanced = _normalize(enhanced)
    enhanced[~np.any(src != 0, axis=2)] = 0
    return enhanced


def _normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis; zero vectors stay zero."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)
