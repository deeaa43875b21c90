"""Ridge enhancement of a normal map (paper Eq. 12, NOTES §4).

n' = n + k (n - normalize(sum_{j in w x w} n_j)), then renormalised: each normal is pushed
away from the mean direction of its w x w neighbourhood, which amplifies the angle between
neighbouring normals and so the visual contrast of the ridges. Paper: w = 7, k = 2.5.
It is for display, applied after the normals are estimated, not for integration.
"""

from __future__ import annotations

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.mask_box import mask_bounding_box
from fingerps_recon.photometric.normal_transform_kernel import enhance_planes


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
    h, w_img = n.shape[:2]
    enhanced = np.zeros((h, w_img, 3), dtype=dtype)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != n.shape[:2] or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape {n.shape[:2]}, got {m.shape} {m.dtype}"
            )
        # Outside the mask's bounding box every normal is zero and stays zero; the box
        # filter's zero border at the box's sides sees the same zeros.
        box = mask_bounding_box(m)
        if box is None:
            return enhanced
        m = m[box]
    else:
        box = (slice(0, h), slice(0, w_img))
        m = None
    block = np.ascontiguousarray(n[box], dtype=dtype)
    x, y, z = cv2.split(block)  # new planes
    # Pixels without a normal (outside the mask, zero or not finite) are zero: they are no
    # neighbours (normalised convolution: the sum is normalised to a direction, so no
    # division by the count is needed) and give zero output.
    if cv2.checkRange(block)[0]:  # all finite (one pass, the usual case)
        finite = None
        keep = m
    else:
        with np.errstate(invalid="ignore"):
            finite = np.abs(x + y + z) < np.inf  # False for NaN and inf
        keep = finite if m is None else finite & m
    if keep is not None and not keep.all():
        for c in (x, y, z):
            c *= keep
        if finite is not None and not finite.all():
            for c in (x, y, z):
                c[~finite] = 0  # NaN * 0 is NaN
    size = (int(w), int(w))
    sx, sy, sz = (
        cv2.boxFilter(c, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
        for c in (x, y, z)
    )
    # n' = (1 + k) n - k s / |s|, renormalised, in place of n (one compiled pass); where no
    # neighbour has a normal (s = 0) the mean direction is n itself, so n' = n up to the
    # scale (1 + k), which the normalisation removes; no normal in, none out.
    enhance_planes(x, y, z, sx, sy, sz, dtype(k), dtype(1.0 + k))
    enhanced[box] = cv2.merge((x, y, z))
    return enhanced
