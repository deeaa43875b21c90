"""One number for "the ridges stand out" in a normal map (for paper Eq. 12, NOTES §4).

The ridges of a fingertip are a narrow band of spatial frequencies (period ~0.5 mm, ~17
pixels on the rig) on top of the finger's smooth shape. :func:`ridge_visibility` measures
how much of the variation of the normals lies in that band: the ratio of the energy of the
ridge band to the energy of everything else (the shape, noise, anything off the ridge
frequency) in the normals' x and y components over the finger. Blurring the normals lowers
it (the ridge band loses energy, the shape keeps it); the ridge enhancement of Eq. 12
raises it (it amplifies deviations from the local mean, the ridges, and leaves the shape).
It is a ratio of energies in the normal map, independent of how the map is displayed.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import scipy.ndimage

from fingerps_recon.errors import FingerpsReconError

# Difference-of-Gaussians band pass: sigma_1 = _DOG_SIGMA * period, sigma_2 = 2 sigma_1;
# its response peaks at the frequency 1 / period (0.153 / sigma_1 for a ratio of 2).
_DOG_SIGMA = 0.153
# Ridge periods searched when the period is estimated, pixels.
_MIN_PERIOD_PX = 4.0
_MAX_PERIOD_PX = 64.0
# At least this many pixels must remain inside the eroded mask.
_MIN_PIXELS = 64


def ridge_visibility(
    normals: np.ndarray, *, mask: np.ndarray, period_px: float | None = None
) -> float:
    """Ridge-band to out-of-band energy ratio of a normal map over a mask.

    With n_x, n_y the normals' x and y components (PS frame), smoothed within the mask
    (normalised Gaussian convolution, so the outside and the mask's edge do not enter):

    - ridge band: b = G(sigma_1) n - G(sigma_2) n, a difference of Gaussians with
      sigma_1 = 0.153 * period, sigma_2 = 2 sigma_1, whose response peaks at the ridge
      frequency 1 / period (and is 0.47 there);
    - the rest: n - mean(n) - b (the finger's shape, noise, other frequencies);
    - visibility = sum |b|^2 / sum |n - mean(n) - b|^2 over the mask eroded by
      ceil(2 sigma_2) pixels (where the smoothing has whole neighbourhoods).

    0 for a map without ridges; it grows as more of the normals' variation is ridges. It
    compares maps of the same finger (before/after an enhancement, two solvers), not
    fingers of different shape (a more curved finger has more out-of-band energy).

    Parameters
    ----------
    normals : (H, W, 3) float
        Normals (PS frame); need not be unit length (they are normalised); zero or
        non-finite vectors are left out.
    mask : (H, W) bool
        The finger.
    period_px : float, optional
        Ridge period in pixels, > 2. None: the peak of the radially averaged power spectrum
        of the high-passed n_x, n_y inside the mask, between 4 and 64 pixels.

    Returns
    -------
    float
        The ratio (dimensionless, >= 0).

    Raises
    ------
    FingerpsReconError
        On bad shapes, a bad period, or a mask too small for the period.
    """
    n = np.asarray(normals, dtype=np.float64)
    m = np.asarray(mask)
    if n.ndim != 3 or n.shape[2] != 3:
        raise FingerpsReconError(f"normals must have shape (H, W, 3), got {n.shape}")
    if m.shape != n.shape[:2] or m.dtype != bool:
        raise FingerpsReconError(
            f"mask must be a bool array of shape {n.shape[:2]}, got {m.shape} {m.dtype}"
        )
    norm = np.linalg.norm(n, axis=2)
    with np.errstate(invalid="ignore"):
        m = m & np.isfinite(norm) & (norm > 0)
    unit = np.divide(n, norm[..., None], out=np.zeros_like(n), where=m[..., None])
    xy = unit[..., :2]
    if period_px is None:
        period = _estimate_period(xy, m)
    else:
        period = float(period_px)
        if not (math.isfinite(period) and period > 2):
            raise FingerpsReconError(f"period_px must be a number > 2 pixels, got {period_px}")
    sigma1 = _DOG_SIGMA * period
    sigma2 = 2.0 * sigma1
    inner = scipy.ndimage.binary_erosion(m, iterations=math.ceil(2 * sigma2))
    if np.count_nonzero(inner) < _MIN_PIXELS:
        raise FingerpsReconError(
            f"the mask has fewer than {_MIN_PIXELS} pixels once eroded by {math.ceil(2 * sigma2)} "
            f"for a ridge period of {period:.1f} px; give a larger mask or a shorter period"
        )
    band = _smooth(xy, m, sigma1) - _smooth(xy, m, sigma2)
    values = xy[inner]
    rest = values - values.mean(axis=0) - band[inner]
    out_of_band = float(np.sum(rest**2))
    in_band = float(np.sum(band[inner] ** 2))
    if out_of_band == 0.0:
        return math.inf if in_band > 0 else 0.0
    return in_band / out_of_band


def _smooth(field: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of ``field`` (H, W, C) using only the pixels inside ``mask``."""
    weight = mask.astype(np.float64)
    num = cv2.GaussianBlur(field * weight[..., None], (0, 0), sigma,
                           borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return np.divide(num, den[..., None], out=np.zeros_like(num), where=den[..., None] > 1e-6)


def _estimate_period(xy: np.ndarray, mask: np.ndarray) -> float:
    """Ridge period (pixels): the peak of the radial power spectrum of the high-passed field."""
    rows, cols = np.nonzero(mask)
    if rows.size < _MIN_PIXELS:
        raise FingerpsReconError(f"the mask has fewer than {_MIN_PIXELS} pixels")
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    sub_mask = mask[box]
    high = xy[box] - _smooth(xy[box], sub_mask, _MAX_PERIOD_PX / 2)
    # Taper the mask's edge so that it does not spread power over all frequencies.
    taper = cv2.GaussianBlur(
        scipy.ndimage.binary_erosion(sub_mask, iterations=4).astype(np.float64), (0, 0), 2.0
    )
    high *= taper[..., None]
    h, w = sub_mask.shape
    power = sum(np.abs(np.fft.rfft2(high[..., c])) ** 2 for c in range(2))
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    radius = np.hypot(fx, fy)
    edges = np.linspace(1.0 / _MAX_PERIOD_PX, 1.0 / _MIN_PERIOD_PX, 121)
    index = np.digitize(radius.ravel(), edges)
    sums = np.bincount(index, weights=power.ravel(), minlength=edges.size + 1)
    counts = np.bincount(index, minlength=edges.size + 1)
    inside = slice(1, edges.size)  # bins between the first and last edge
    mean_power = sums[inside] / np.maximum(counts[inside], 1)
    if not np.any(mean_power > 0):
        raise FingerpsReconError(
            "no ridge frequency found (the normals do not vary inside the mask); give period_px"
        )
    peak = int(np.argmax(mean_power))
    centres = 0.5 * (edges[:-1] + edges[1:])
    frequency = centres[peak]
    if 0 < peak < mean_power.size - 1:  # parabola through the peak and its neighbours
        left, mid, right = mean_power[peak - 1:peak + 2]
        curvature = left - 2 * mid + right
        if curvature < 0:
            frequency += 0.5 * (left - right) / curvature * (centres[1] - centres[0])
    return 1.0 / frequency
