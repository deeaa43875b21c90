"""The finger's mask from a burst: where some LED lights it clearly above the background."""

from __future__ import annotations

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError


def finger_mask(images: np.ndarray, *, threshold: float = 0.15, open_px: int = 5) -> np.ndarray:
    """Return the (H, W) bool mask of the largest bright region of a burst.

    Parameters
    ----------
    images : (K, H, W) float
        The burst (dark-subtracted where a dark frame exists).
    threshold : float
        A pixel belongs to the finger when its brightest value over the LEDs exceeds
        ``threshold`` times the 99th percentile of those values, in (0, 1).
    open_px : int
        Size of the morphological opening and closing that remove specks and holes.
    """
    stack = np.asarray(images, dtype=np.float32)
    if stack.ndim != 3:
        raise FingerpsReconError(f"images must be (K, H, W), got shape {stack.shape}")
    if not 0.0 < threshold < 1.0:
        raise FingerpsReconError(f"threshold must be in (0, 1), got {threshold}")
    brightest = stack.max(axis=0)
    level = float(np.percentile(brightest, 99.0))
    if level <= 0.0:
        return np.zeros(brightest.shape, dtype=bool)
    binary = (brightest > threshold * level).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (open_px, open_px))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if count <= 1:
        return np.zeros(brightest.shape, dtype=bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == largest
