"""The relative light intensities e_k (paper Eq. 3) as the photometric-stereo solvers take
them: one number per light, or one per light and pixel (the near-light irradiance)."""

from __future__ import annotations

import numpy as np

from fingerps_recon.errors import FingerpsReconError


def checked_intensities(intensities: np.ndarray | None, *,
                        shape: tuple[int, int, int]) -> np.ndarray:
    """The intensities checked against the images' shape; all ones when None.

    Parameters
    ----------
    intensities : (K,) or (K, H, W) float, optional
        Relative light intensities e_k; per light they must be finite and > 0 (per pixel
        the solvers leave out a light whose intensity is not).
    shape : (K, H, W)
        The images' shape.

    Returns
    -------
    (K,) float64 or (K, H, W) as given
        A new array for (K,); the input itself (not copied) for (K, H, W).

    Raises
    ------
    FingerpsReconError
        On another shape, or a per-light intensity that is not finite and > 0.
    """
    k, h, w = shape
    if intensities is None:
        return np.ones(k)
    e = np.asarray(intensities)
    if e.shape not in ((k,), (k, h, w)):
        raise FingerpsReconError(
            f"intensities must have shape (K,) = ({k},) or (K, H, W) = ({k}, {h}, {w}), "
            f"got {e.shape}"
        )
    if e.ndim == 1:
        e = e.astype(np.float64)
        if not np.all(np.isfinite(e) & (e > 0)):
            raise FingerpsReconError(f"intensities must be finite and > 0, got {e}")
    return e
