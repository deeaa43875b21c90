"""Synthetic fingerprints in the spirit of SFinGe: ridges grown by contextual Gabor filtering.

SFinGe (Cappelli, Maio & Maltoni, "Synthetic fingerprint-image generation", ICPR 2000; the
Handbook of Fingerprint Recognition, ch. "Synthetic fingerprint generation"): a pattern class
and its singular points give an orientation field (``fingerprint_orientation``: the zero-pole
model of Sherlock & Monro 1993 with the Vizcaya-Gerhardt correction), a ridge-period map is
drawn, and the ridges are grown from a few random seeds by iterative space-variant Gabor
filtering, each pixel with the filter tuned to its orientation and period, clipped to [-1, 1]
between iterations. Where fronts grown from different seeds meet out of phase, or the period
changes, ridge endings and bifurcations arise by themselves.

An identity is an integer seed: ``generate_fingerprint(seed)`` always returns the same finger,
different seeds different fingers. The ground-truth minutiae are read from the skeleton of the
final binary pattern (``fingerprint_minutiae``). Coordinates and angle conventions: see
``fingerprint_orientation`` (mm in the rolled plane, x right, y down, angles counter-clockwise
on the image).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from fingerps_driver.simulation.fingerprint_minutiae import Minutia, extract_minutiae
from fingerps_driver.simulation.fingerprint_orientation import (
    OrientationModel,
    PatternClass,
    SingularPoint,
    draw_class,
    draw_model,
    orientation_field,
    period_map,
)

PIXEL_MM_500PPI = 25.4 / 500.0

_ORIENTATION_BINS = 16
_PERIOD_BINS = 3
_SIGMA_ACROSS = 0.75  # Gabor envelope across the ridges, in periods
_SIGMA_ALONG = 0.9  # and along them
_SEEDS_PER_MM2 = 0.05


@dataclass(frozen=True)
class FingerprintPattern:
    """One synthetic finger in the rolled plane.

    Attributes
    ----------
    seed : int
        The identity.
    pattern_class : PatternClass
    ridges : (H, W) float32
        Ridge pattern in [-1, 1], ridges +1, valleys -1 (smooth flanks).
    pixel_mm : float
        Side of a grid pixel on the skin (mm).
    orientation_rad : (H, W) float32
        Ridge orientation in [0, pi), counter-clockwise on the image.
    period_mm : (H, W) float32
        Ridge period map the ridges were grown with.
    mask : (H, W) bool
        The fingertip's area in the rolled print (a rectangle with a rounded top).
    singular_points : tuple of SingularPoint
    minutiae : tuple of Minutia
        Ground truth, from the skeleton of ``ridges > 0``.
    """

    seed: int
    pattern_class: PatternClass
    ridges: np.ndarray
    pixel_mm: float
    orientation_rad: np.ndarray
    period_mm: np.ndarray
    mask: np.ndarray
    singular_points: tuple[SingularPoint, ...]
    minutiae: tuple[Minutia, ...]

    @property
    def width_mm(self) -> float:
        return self.ridges.shape[1] * self.pixel_mm

    @property
    def height_mm(self) -> float:
        return self.ridges.shape[0] * self.pixel_mm


def generate_fingerprint(
    seed: int,
    *,
    pattern_class: PatternClass | None = None,
    width_mm: float = 20.0,
    height_mm: float = 25.0,
    pixel_mm: float = PIXEL_MM_500PPI,
    period_range_mm: tuple[float, float] = (0.40, 0.55),
    iterations: int = 32,
) -> FingerprintPattern:
    """The synthetic finger of identity ``seed`` (SFinGe-style, see the module docstring).

    ``pattern_class`` None draws it from the seed with the natural class frequencies.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5F1D6E]))
    if pattern_class is None:
        pattern_class = draw_class(rng)
    shape = (round(height_mm / pixel_mm), round(width_mm / pixel_mm))
    model: OrientationModel = draw_model(pattern_class, rng, width_mm=width_mm, height_mm=height_mm)
    theta = orientation_field(model, shape, pixel_mm=pixel_mm)
    period = period_map(shape, rng, pixel_mm=pixel_mm, period_range_mm=period_range_mm)
    ridges = grow_ridges(theta, period, rng, pixel_mm=pixel_mm, iterations=iterations)
    mask = fingertip_mask(shape, pixel_mm=pixel_mm)
    minutiae = extract_minutiae(
        ridges, pixel_mm=pixel_mm, orientation_rad=theta, mask=mask,
        singular_points=model.singular_points,
    )
    return FingerprintPattern(
        seed=int(seed),
        pattern_class=pattern_class,
        ridges=ridges,
        pixel_mm=float(pixel_mm),
        orientation_rad=theta.astype(np.float32),
        period_mm=period.astype(np.float32),
        mask=mask,
        singular_points=model.singular_points,
        minutiae=minutiae,
    )


def fingertip_mask(shape: tuple[int, int], *, pixel_mm: float) -> np.ndarray:
    """The rolled print's outline: the full grid width, a semicircular top, a flat bottom."""
    rows, cols = shape
    half_w = cols * pixel_mm / 2
    x = (np.arange(cols) + 0.5) * pixel_mm - half_w
    y = (np.arange(rows) + 0.5) * pixel_mm
    above = np.maximum(half_w - y, 0.0)[:, None]
    return (x[None, :] ** 2 + above**2) <= half_w**2


def _gabor_transfer(fft_shape: tuple[int, int], period_px: float, theta: float) -> np.ndarray:
    """Transfer function (fy, fx//2+1) of an even Gabor filter, unit gain at its peak.

    Anisotropic Gaussian envelope (``_SIGMA_ACROSS`` / ``_SIGMA_ALONG`` periods), wave vector
    across ridges of orientation ``theta``; built in the frequency domain, DC removed.
    """
    fy = scipy.fft.fftfreq(fft_shape[0])[:, None]
    fx = scipy.fft.rfftfreq(fft_shape[1])[None, :]
    # Ridge tangent (cos, -sin) in (column, row) axes; the wave runs along the normal.
    nx, ny = -np.sin(theta), -np.cos(theta)
    tx, ty = np.cos(theta), -np.sin(theta)
    resp = np.zeros((fy.shape[0], fx.shape[1]))
    for sign in (1.0, -1.0):
        dx, dy = fx - sign * nx / period_px, fy - sign * ny / period_px
        across, along = dx * nx + dy * ny, dx * tx + dy * ty
        resp += np.exp(
            -2 * np.pi**2 * period_px**2
            * (_SIGMA_ACROSS**2 * across**2 + _SIGMA_ALONG**2 * along**2)
        )
    resp[0, 0] = 0.0
    return resp.astype(np.float32)


class _ContextualGabor:
    """Space-variant Gabor filtering on one grid: a bank of filters (orientation x period
    bins) applied by FFT with a zero margin (no wrap-around), each pixel taking the response
    bilinearly interpolated to its own orientation and period."""

    def __init__(self, orientation_rad: np.ndarray, period_px: np.ndarray) -> None:
        shape = orientation_rad.shape
        margin = int(np.ceil(3 * _SIGMA_ALONG * period_px.max()))
        fft_shape = (
            scipy.fft.next_fast_len(shape[0] + 2 * margin, real=True),
            scipy.fft.next_fast_len(shape[1] + 2 * margin, real=True),
        )
        periods = np.geomspace(period_px.min(), period_px.max() * (1 + 1e-6), _PERIOD_BINS)
        fp = np.interp(np.log(period_px), np.log(periods), np.arange(_PERIOD_BINS))
        p0 = np.minimum(np.floor(fp).astype(int), _PERIOD_BINS - 2)
        wp = fp - p0
        fo = np.mod(orientation_rad, np.pi) / (np.pi / _ORIENTATION_BINS)
        o0 = np.floor(fo).astype(int) % _ORIENTATION_BINS
        wo = fo - np.floor(fo)
        o1 = (o0 + 1) % _ORIENTATION_BINS
        bins = np.stack([(p0 + a) * _ORIENTATION_BINS + o for a in (0, 1) for o in (o0, o1)])
        weights = np.stack([(1 - wp) * (1 - wo), (1 - wp) * wo, wp * (1 - wo), wp * wo])
        needed, slot = np.unique(bins, return_inverse=True)
        self.bank = np.stack([
            _gabor_transfer(
                fft_shape, periods[b // _ORIENTATION_BINS],
                (b % _ORIENTATION_BINS) * np.pi / _ORIENTATION_BINS,
            )
            for b in needed
        ])
        rows, cols = np.indices(shape)
        pixel = (rows + margin) * fft_shape[1] + cols + margin
        plane = fft_shape[0] * fft_shape[1]
        self.index = (slot.reshape(bins.shape) * plane + pixel).reshape(4, -1)
        self.weights = weights.reshape(4, -1).astype(np.float32)
        self.shape, self.fft_shape, self.margin = shape, fft_shape, margin
        self.padded = np.zeros(fft_shape, np.float32)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        m = self.margin
        self.padded[m:m + self.shape[0], m:m + self.shape[1]] = image
        spectrum = scipy.fft.rfft2(self.padded, workers=-1)
        filtered = scipy.fft.irfft2(self.bank * spectrum, s=self.fft_shape, workers=-1)
        out = (filtered.reshape(-1)[self.index] * self.weights).sum(axis=0)
        return out.reshape(self.shape)


def _downsample_orientation(theta: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    c = cv2.resize(np.cos(2 * theta), size, interpolation=cv2.INTER_AREA)
    s = cv2.resize(np.sin(2 * theta), size, interpolation=cv2.INTER_AREA)
    return np.mod(0.5 * np.arctan2(s, c), np.pi)


def grow_ridges(
    orientation_rad: np.ndarray,
    period_mm: np.ndarray,
    rng: np.random.Generator,
    *,
    pixel_mm: float,
    iterations: int = 32,
    final_iterations: int = 3,
    seeds_per_mm2: float = _SEEDS_PER_MM2,
) -> np.ndarray:
    """Ridges grown from random seeds by iterative contextual Gabor filtering (SFinGe).

    Random seeds (single-pixel spikes of random sign, ``seeds_per_mm2``) are filtered with
    the Gabor filter tuned to each pixel's orientation and period (``_ORIENTATION_BINS`` x
    ``_PERIOD_BINS`` bins, interpolated), the response amplified and clipped to [-1, 1], and
    again, so that the ridge patches grow and meet. Coarse to fine: ``iterations`` on a grid
    of twice the pixel (the ridges still have >= 4 px a period there), then
    ``final_iterations`` on the full grid. The last response is normalised by its local
    amplitude and softly clipped: ridges with flat tops and smooth flanks.

    Returns
    -------
    ridges : (H, W) float32 in [-1, 1], ridges +1.
    """
    shape = orientation_rad.shape
    coarse_size = (max(8, shape[1] // 2), max(8, shape[0] // 2))
    coarse_pixel = pixel_mm * shape[1] / coarse_size[0]
    theta_c = _downsample_orientation(orientation_rad, coarse_size)
    period_c = cv2.resize(period_mm, coarse_size, interpolation=cv2.INTER_AREA) / coarse_pixel
    coarse = _ContextualGabor(theta_c, period_c)

    image = np.zeros(theta_c.shape, np.float32)
    area_mm2 = shape[0] * shape[1] * pixel_mm**2
    n_seeds = max(1, int(rng.poisson(seeds_per_mm2 * area_mm2)))
    rows = rng.integers(0, theta_c.shape[0], n_seeds)
    cols = rng.integers(0, theta_c.shape[1], n_seeds)
    image[rows, cols] = rng.choice([-1.0, 1.0], n_seeds) * 20.0
    for _ in range(iterations):
        image = np.clip(2.5 * coarse(image), -1.0, 1.0)

    fine = _ContextualGabor(orientation_rad, period_mm / pixel_mm)
    image = cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    for _ in range(final_iterations):
        out = fine(image)
        image = np.clip(2.5 * out, -1.0, 1.0)
    amplitude = cv2.GaussianBlur(np.abs(out), (0, 0), float(np.median(period_mm)) / pixel_mm)
    return np.clip(1.6 * out / (amplitude + 1e-6), -1.0, 1.0).astype(np.float32)


def render_rolled_print(pattern: FingerprintPattern, *, ppi: float = 500.0) -> np.ndarray:
    """The rolled print as an inked card shows it: uint8, ridges dark, white outside the finger.

    Resampled from the pattern's grid to ``ppi`` (500 ppi: 19.685 px/mm) when they differ.

    Returns
    -------
    image : (H', W') uint8
    """
    grey = 127.5 * (1.0 - pattern.ridges.astype(np.float32))
    grey[~pattern.mask] = 255.0
    scale = pattern.pixel_mm * ppi / 25.4
    if abs(scale - 1.0) > 1e-6:
        size = (round(grey.shape[1] * scale), round(grey.shape[0] * scale))
        interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
        grey = cv2.resize(grey, size, interpolation=interpolation)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)

