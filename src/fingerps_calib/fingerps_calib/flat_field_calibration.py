"""Correction of the lighting field from images of a white flat target (paper Eq. 11).

Under LED k the white target gives W_k(i, j); the portion p_k = W_k / max W_k is a property
of the LED (its position, lobe and fall-off), not of the object: dividing a later image
under LED k by p_k makes its illumination uniform (../shared/paper/NOTES.md Sec. 3.2).

A raw W_k also holds the target's paper texture, dust and sensor noise, which must not end
up in the map. Each W_k is therefore smoothed first:

- `Smoothing.POLYNOMIAL` (default): least-squares fit of a 2D polynomial of total degree
  ``polynomial_degree`` (4) over the whole image, fitted to block means (64 blocks across
  the short side). An LED's field on a plane (inverse square, cosine, emission lobe, lens
  vignetting) is this smooth; on the simulated rig (fingerps_driver.simulation) degree 4
  follows it to 0.3 % at worst, texture and noise included, where degree 2 leaves 1 % and
  degree 8 starts to fit the noise.
- `Smoothing.LOCAL_LINEAR`: Gaussian-weighted local linear regression, i.e. a Gaussian
  filter of ``smoothing_sigma_px`` whose weights are renormalised and corrected for the
  local slope, so it has no bias at the image border (where a plain Gaussian filter with a
  reflected or clamped border flattens the fall-off). Local, so it follows features a
  polynomial cannot, but noisier in the corners and biased by the field's curvature
  (sigma^2 / 2 times its second derivative); on the simulated rig 0.5 % at worst with
  sigma = 20 px, and about ten times slower.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import cv2
import numpy as np

from fingerps_calib.errors import FingerpsCalibError

#: Portions are clipped below at this value so that dividing by them stays finite.
MIN_PORTION = 1e-3

#: Smallest width and height (pixels) of a white-target image. The smooth field is fitted to
#: (and its residual measured on) the means of blocks, 64 across the short side, so that
#: paper texture and noise average out; a smaller image has blocks of one pixel or none (a
#: 1x1 image made the fit fail, a 0x0 one crash), and no real sensor is that small.
MIN_IMAGE_SIDE_PX = 64


class Smoothing(Enum):
    """How each white-target image is smoothed before it becomes a portion map."""

    LOCAL_LINEAR = "local_linear"
    POLYNOMIAL = "polynomial"


@dataclass(frozen=True, eq=False)
class FlatFieldResult:
    """Flat-field maps of K LEDs (paper Eq. 11).

    Attributes
    ----------
    portions : (K, H, W) float32
        p_k = smoothed W_k / max(smoothed W_k), in [MIN_PORTION, 1]; the maximum of each
        map is 1.
    relative_intensities : (K,) float64
        Mean of each smoothed W_k over the image, divided by the largest of these means
        (the brightest LED has 1).
    fit_residuals : (K,) float64
        How far each W_k departs from its smooth field: the rms over blocks (the ~64 blocks
        across the short side of `Smoothing.POLYNOMIAL`) of (block mean of W_k - block mean
        of the smoothed W_k), as a fraction of the smoothed W_k's peak. Block means keep
        most of the sensor noise and paper texture out of it, so it measures structure: a
        fold, a shadow, a stain, an object in view. 0.5 % on the simulated rig (0.7 % with
        four times the read noise); ~2 % for a point light closer to the target than its
        width (the degree-4 polynomial's own misfit); a folded card with a 20 % step
        3.7 %, a shadow 13 %, a finger in view tens of percent.
    """

    portions: np.ndarray
    relative_intensities: np.ndarray
    fit_residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))


def flat_field_maps(
    images: np.ndarray,
    *,
    smoothing_sigma_px: float = 20.0,
    dark: np.ndarray | float | None = None,
    smoothing: Smoothing = Smoothing.POLYNOMIAL,
    polynomial_degree: int = 4,
    saturation_level: float | None = None,
    max_saturated_fraction: float = 1e-3,
    min_signal_fraction: float = 0.02,
    max_fit_residual: float | None = 0.03,
) -> FlatFieldResult:
    """Portion maps p_k of K LEDs from images of a white flat target (paper Eq. 11).

    Parameters
    ----------
    images : (K, H, W) array, any real dtype
        W_k: the white target under LED k alone; H, W >= `MIN_IMAGE_SIDE_PX`.
    smoothing_sigma_px : float
        Gaussian sigma of `Smoothing.LOCAL_LINEAR`, pixels; large against the paper's
        texture, small against the field's variation.
    dark : float or (H, W) or (K, H, W) array, optional
        Dark level or frame(s) (all LEDs off), subtracted first.
    smoothing : Smoothing
        See the module docstring.
    polynomial_degree : int
        Total degree of `Smoothing.POLYNOMIAL`.
    saturation_level : float, optional
        Full-scale value; default the dtype's maximum for integer images, 1.0 for floats.
    max_saturated_fraction : float
        A W_k with more of its pixels at ``saturation_level`` is refused.
    min_signal_fraction : float
        A W_k whose 99th percentile (after the dark) is below this fraction of
        ``saturation_level`` is refused as nearly black.
    max_fit_residual : float or None
        A W_k whose ``fit_residuals`` exceeds this is refused: the target is not flat and
        uniform, or something else is in view. None: no check.

    Returns
    -------
    FlatFieldResult

    Raises
    ------
    FingerpsCalibError
        Bad shapes or options; a saturated, nearly black or not smooth image (the message
        names the LEDs and says what to do).
    """
    stack = np.asarray(images)
    if stack.ndim != 3 or stack.shape[0] < 1 or not np.issubdtype(stack.dtype, np.number):
        raise FingerpsCalibError(
            f"images has shape {stack.shape} ({stack.dtype}), expected (K, H, W) numbers, "
            "one white-target image per LED"
        )
    if min(stack.shape[1:]) < MIN_IMAGE_SIDE_PX:
        raise FingerpsCalibError(
            f"the white-target images are {stack.shape[2]}x{stack.shape[1]} px; the flat "
            f"field needs at least {MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX} (the smooth field "
            "is fitted to 64 blocks across the short side): capture full camera frames"
        )
    if np.issubdtype(stack.dtype, np.floating) and not np.all(np.isfinite(stack)):
        raise FingerpsCalibError(
            "the white-target images hold NaN or infinite pixels; capture them again")
    if not smoothing_sigma_px > 0:
        raise FingerpsCalibError(f"smoothing_sigma_px = {smoothing_sigma_px} must be > 0")
    if not isinstance(smoothing, Smoothing):
        raise FingerpsCalibError(f"smoothing must be a Smoothing, got {smoothing!r}")
    if saturation_level is None:
        integer = np.issubdtype(stack.dtype, np.integer)
        saturation_level = float(np.iinfo(stack.dtype).max) if integer else 1.0
    n_led, h, w = stack.shape
    values = stack.astype(np.float64)
    for k in range(n_led):
        fraction = np.mean(values[k] >= saturation_level)
        if fraction > max_saturated_fraction:
            raise FingerpsCalibError(
                f"LED {k}: {100 * fraction:.2f}% of the white-target pixels are saturated "
                f"(>= {saturation_level:g}); lower the exposure or the LED current and "
                "capture the white target again"
            )
    if dark is not None:
        dark = np.asarray(dark, dtype=np.float64)
        if dark.shape not in ((), (h, w), (n_led, h, w)):
            raise FingerpsCalibError(
                f"dark has shape {dark.shape}, expected a scalar level, ({h}, {w}) or "
                f"({n_led}, {h}, {w})"
            )
        values = values - dark
    for k in range(n_led):
        level = np.percentile(values[k], 99.0)
        if level < min_signal_fraction * saturation_level:
            raise FingerpsCalibError(
                f"LED {k}: the white-target image is nearly black (99th percentile "
                f"{level:.3g} of full scale {saturation_level:g}); check that LED {k} lights, "
                "that the target fills the view, and the exposure"
            )
    if smoothing is Smoothing.LOCAL_LINEAR:
        smooth = _local_linear(values, smoothing_sigma_px)
    else:
        smooth = _polynomial(values, polynomial_degree)
    peaks = smooth.reshape(n_led, -1).max(axis=1)
    if not np.all(peaks > 0):
        raise FingerpsCalibError(
            f"LED {int(np.argmin(peaks))}: the smoothed white-target image is not positive; "
            "is the dark frame brighter than the image?"
        )
    residuals = _block_residuals(values, smooth) / peaks
    if max_fit_residual is not None and np.any(residuals > max_fit_residual):
        bad = np.flatnonzero(residuals > max_fit_residual)
        listed = ", ".join(f"LED {k} {100 * residuals[k]:.1f}%" for k in bad)
        raise FingerpsCalibError(
            f"the white-target images depart from a smooth lighting field ({listed} rms; at "
            f"most {100 * max_fit_residual:.1f}%): the target is not flat and uniform, or "
            "something else is in view; use a flat, clean, matte white card that fills the "
            "view and capture again"
        )
    portions = np.clip(smooth / peaks[:, None, None], MIN_PORTION, 1.0).astype(np.float32)
    means = smooth.reshape(n_led, -1).mean(axis=1)
    return FlatFieldResult(portions=portions, relative_intensities=means / means.max(),
                           fit_residuals=residuals)


def _block_residuals(values: np.ndarray, smooth: np.ndarray) -> np.ndarray:
    """(K,) rms over blocks of block-mean(values - smooth), in the images' units."""
    n_led, h, w = values.shape
    b = max(1, min(h, w) // 64)
    hb, wb = h // b, w // b
    diff = (values - smooth)[:, : hb * b, : wb * b].reshape(n_led, hb, b, wb, b)
    return np.sqrt(np.mean(diff.mean(axis=(2, 4)) ** 2, axis=(1, 2)))


def _local_linear(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted local linear fit of each (H, W) image, evaluated at each pixel."""
    n_led, h, w = values.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    ys, xs = (ys - h / 2) / sigma, (xs - w / 2) / sigma  # centred, in units of sigma

    def blur(a: np.ndarray) -> np.ndarray:
        # Zero outside the image: the weights are renormalised by m0 below.
        return cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)

    m0 = blur(np.ones_like(xs))
    mx, my = blur(xs) / m0, blur(ys) / m0
    cxx = blur(xs * xs) / m0 - mx * mx
    cxy = blur(xs * ys) / m0 - mx * my
    cyy = blur(ys * ys) / m0 - my * my
    det = cxx * cyy - cxy * cxy
    out = np.empty_like(values)
    for k in range(n_led):
        f = values[k]
        mf = blur(f) / m0
        cxf = blur(xs * f) / m0 - mx * mf
        cyf = blur(ys * f) / m0 - my * mf
        bx = (cyy * cxf - cxy * cyf) / det
        by = (cxx * cyf - cxy * cxf) / det
        out[k] = mf + bx * (xs - mx) + by * (ys - my)
    return out


def _polynomial(values: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares 2D polynomial of total ``degree`` fitted to each (H, W) image."""
    if not 0 <= degree <= 12:
        raise FingerpsCalibError(f"polynomial_degree = {degree} must lie in 0..12")
    n_led, h, w = values.shape
    # Fitted to the means of b x b blocks (all pixels count, the problem stays small),
    # placed at the blocks' centres. Legendre polynomials in coordinates scaled to [-1, 1]
    # keep it well conditioned; terms P_i(x) P_j(y) with i + j <= degree.
    b = max(1, min(h, w) // 64)
    hb, wb = h // b, w // b
    blocks = values[:, : hb * b, : wb * b].reshape(n_led, hb, b, wb, b).mean(axis=(2, 4))

    def scaled(centres: np.ndarray, size: int) -> np.ndarray:
        return 2.0 * centres / (size - 1) - 1.0

    def basis(x: np.ndarray) -> np.ndarray:
        return np.polynomial.legendre.legvander(x, degree)

    bx = basis(scaled(np.arange(wb) * b + (b - 1) / 2, w))  # (wb, D)
    by = basis(scaled(np.arange(hb) * b + (b - 1) / 2, h))  # (hb, D)
    terms = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    design = np.stack([np.outer(by[:, j], bx[:, i]).ravel() for i, j in terms], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, blocks.reshape(n_led, -1).T, rcond=None)  # (T, K)
    px = basis(scaled(np.arange(w, dtype=np.float64), w))
    py = basis(scaled(np.arange(h, dtype=np.float64), h))
    out = np.empty(values.shape)
    for k in range(n_led):
        c = np.zeros((degree + 1, degree + 1))  # c[j, i] multiplies P_j(y) P_i(x)
        for (i, j), value in zip(terms, coeffs[:, k], strict=True):
            c[j, i] = value
        out[k] = py @ c @ px.T
    return out
