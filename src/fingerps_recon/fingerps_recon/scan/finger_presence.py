"""Is a finger in the field, where, and how much of it: from a dark and a lit frame.

A cheap check before a scan: the lit frame minus the dark frame (ambient light and the
sensor's offset cancel), smoothed, thresholded at a fraction of full scale; the largest
connected bright region is the finger. Any frame lit by one LED will do (the first frame
of a burst, with the burst's dark frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError


@dataclass(frozen=True)
class FingerPresence:
    """Result of :func:`detect_finger`.

    Attributes
    ----------
    present : bool
        A region covering at least ``min_coverage`` of the image stands out.
    coverage : float
        The largest bright region's area / the image's area (0 when nothing stands out).
    bbox : (row0, col0, row1, col1) or None
        The region's bounding box, rows and columns, end exclusive.
    centroid : (row, col) or None
        The region's centre in pixels.
    """

    present: bool
    coverage: float
    bbox: tuple[int, int, int, int] | None
    centroid: tuple[float, float] | None

    def describe(self) -> str:
        """One line for people: where the finger is and how much of the image it fills."""
        if self.bbox is None or self.centroid is None:
            return "no finger in view"
        r0, c0, r1, c1 = self.bbox
        what = "finger" if self.present else "too small a bright region"
        return (f"{what} at row {self.centroid[0]:.0f}, column {self.centroid[1]:.0f} "
                f"(rows {r0}..{r1}, columns {c0}..{c1}), {100 * self.coverage:.0f}% of the "
                "image")


def detect_finger(
    lit: np.ndarray,
    *,
    dark: np.ndarray | None = None,
    full_scale: float,
    threshold: float = 0.05,
    min_coverage: float = 0.05,
    smoothing_px: int = 5,
) -> FingerPresence:
    """Find the finger in a lit frame.

    Parameters
    ----------
    lit : (H, W) uint8/uint16/float
        A frame lit by one LED. Not modified.
    dark : (H, W), optional
        An all-LEDs-off frame of the same scene, subtracted first.
    full_scale : float
        The sensor's largest value (255, 4095...).
    threshold : float
        A pixel is bright when (lit - dark), box-smoothed over ``smoothing_px``, exceeds
        this fraction of ``full_scale``.
    min_coverage : float
        Smallest fraction of the image the largest bright region must cover to count as a
        finger.
    smoothing_px : int
        Box filter size, pixels (>= 1).

    Returns
    -------
    FingerPresence

    Raises
    ------
    FingerpsReconError
        Bad shapes or options.
    """
    image = np.asarray(lit, dtype=np.float32)
    if image.ndim != 2 or image.size == 0:
        raise FingerpsReconError(f"lit must be one (H, W) image, got shape {image.shape}")
    if dark is not None:
        if np.shape(dark) != image.shape:
            raise FingerpsReconError(
                f"dark frame {np.shape(dark)} differs from the lit frame {image.shape}")
        image = image - np.asarray(dark, dtype=np.float32)
    if not (math.isfinite(full_scale) and full_scale > 0):
        raise FingerpsReconError(f"full_scale must be > 0, got {full_scale}")
    if not 0 < threshold < 1 or not 0 <= min_coverage <= 1 or smoothing_px < 1:
        raise FingerpsReconError(
            "threshold must be in (0, 1), min_coverage in [0, 1] and smoothing_px >= 1")
    smooth = cv2.blur(image, (int(smoothing_px), int(smoothing_px)))
    bright = (smooth > threshold * full_scale).astype(np.uint8)
    count, _labels, stats, centroids = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if count <= 1:
        return FingerPresence(False, 0.0, None, None)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h, area = (int(v) for v in stats[largest])
    coverage = area / image.size
    cx, cy = (float(v) for v in centroids[largest])
    return FingerPresence(coverage >= min_coverage, coverage, (y, x, y + h, x + w), (cy, cx))
