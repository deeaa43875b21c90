"""The finger's mask from a burst: where some LED lights it clearly above the background."""

from __future__ import annotations

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError

# Counts below this are exact in float32 (OpenCV's histograms count in float32).
_EXACT_FLOAT32_COUNT = 2**24


def finger_mask(images: np.ndarray, *, threshold: float = 0.15, open_px: int = 5,
                saturation_level: float | None = None) -> np.ndarray:
    """Return the (H, W) bool mask of the largest bright region of a burst.

    Parameters
    ----------
    images : (K, H, W) float or int
        The burst (dark-subtracted where a dark frame exists); read as it is (uint8, uint16,
        float32; other dtypes as float32), not modified.
    threshold : float
        A pixel belongs to the finger when its brightest value over the LEDs exceeds
        ``threshold`` times the 99th percentile of those values, in (0, 1).
    open_px : int
        Size of the morphological opening and closing that remove specks and holes.
    saturation_level : float, optional
        Values at or above it are saturated and count as 0 (dark) here; default none.
    """
    stack = np.asarray(images)
    if stack.ndim != 3:
        raise FingerpsReconError(f"images must be (K, H, W), got shape {stack.shape}")
    if not 0.0 < threshold < 1.0:
        raise FingerpsReconError(f"threshold must be in (0, 1), got {threshold}")
    if stack.dtype not in (np.uint8, np.uint16, np.float32):
        stack = stack.astype(np.float32)
    brightest = _brightest(stack, saturation_level)
    level = _percentile_99(brightest)
    if level <= 0.0:
        return np.zeros(brightest.shape, dtype=bool)
    binary = (brightest > threshold * level).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (open_px, open_px))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    # Labels without OpenCV's statistics (several times slower), the areas by a count.
    count, labels = cv2.connectedComponents(binary, connectivity=8)
    if count <= 1:
        return np.zeros(brightest.shape, dtype=bool)
    if count == 2:  # one region (the usual case): no areas to compare
        return labels == 1
    areas = np.bincount(labels.reshape(-1), minlength=count)
    largest = 1 + int(np.argmax(areas[1:]))
    return labels == largest


def _brightest(stack: np.ndarray, saturation_level: float | None) -> np.ndarray:
    """Per pixel, the largest value over the images, saturated values counting as 0."""
    if saturation_level is None or not stack.reshape(stack.shape[0], -1).max() >= \
            saturation_level:
        return stack.max(axis=0)
    if stack.dtype.kind == "u":  # v >= level  <=>  v > ceil(level) - 1 for integers v
        cut = float(np.ceil(saturation_level) - 1.0)
    else:  # float32: the largest float32 below the level, as a float32 threshold
        cut = np.float32(saturation_level)
        while cut >= saturation_level:
            cut = np.nextafter(cut, np.float32(-np.inf))
        cut = float(cut)
    brightest = None
    for image in stack:  # v > cut -> 0, one image at a time (OpenCV, no temporaries)
        _, kept = cv2.threshold(image, cut, 0, cv2.THRESH_TOZERO_INV)
        brightest = kept if brightest is None else cv2.max(brightest, kept, dst=brightest)
    return brightest


def _percentile_99(values: np.ndarray) -> float:
    """numpy's 99th percentile (linear interpolation between order statistics) of
    ``values``; for 8-bit values from their histogram instead of a partition."""
    flat = values.reshape(-1)
    if flat.dtype != np.uint8:
        return float(np.percentile(flat, 99.0))
    position = 0.99 * (flat.size - 1)
    low = int(np.floor(position))
    high = min(low + 1, flat.size - 1)
    if flat.size < _EXACT_FLOAT32_COUNT:  # OpenCV's histogram (float32 counts, exact here)
        counts = cv2.calcHist([flat], [0], None, [256], [0, 256]).reshape(-1).astype(np.int64)
    else:
        counts = np.bincount(flat, minlength=256)
    cumulative = np.cumsum(counts)
    v_low, v_high = np.searchsorted(cumulative, [low + 1, high + 1])
    return float(v_low + (position - low) * (float(v_high) - float(v_low)))
