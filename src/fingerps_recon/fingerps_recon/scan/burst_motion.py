"""Did the finger move during a burst: the first LED's frame against its repeat.

The driver lights the burst's first LED again after the last one (``repeat_first_led``);
the same light on a still finger gives the same image, so the translation between the two
frames, by phase correlation (``cv2.phaseCorrelate``, Hann window, sub-pixel), is how far
the finger moved during the burst. Whole-pixel shifts come out exact; the sub-pixel part is
OpenCV's centroid of the correlation peak, up to ~0.3 px off for half-pixel shifts of a
random texture (0.03 px on the simulated finger) - well below the motion limits used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError


@dataclass(frozen=True)
class BurstMotion:
    """Result of :func:`estimate_motion`.

    Attributes
    ----------
    shift_px : (du, dv)
        Translation of ``repeat`` relative to ``first``, pixels (columns, rows).
    magnitude_px : float
        Length of ``shift_px``.
    correlation : float
        Peak of the phase correlation, 0..1 (near 1: the same image shifted; low: the two
        frames differ by more than a shift, or carry little texture).
    """

    shift_px: tuple[float, float]
    magnitude_px: float
    correlation: float


def estimate_motion(first: np.ndarray, repeat: np.ndarray) -> BurstMotion:
    """Translation between two frames of the same LED.

    Parameters
    ----------
    first, repeat : (H, W) uint8/uint16/float
        The first LED's frame and its repeat at the end of the burst. Not modified.

    Returns
    -------
    BurstMotion

    Raises
    ------
    FingerpsReconError
        Different or non-2-D shapes.
    """
    a = np.asarray(first, dtype=np.float64)
    b = np.asarray(repeat, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape or min(a.shape) < 8:
        raise FingerpsReconError(
            f"first and repeat must be (H, W) images of one size (>= 8 px), got {a.shape} "
            f"and {b.shape}")
    # phaseCorrelate pads to cv2.getOptimalDFTSize, and an odd padded size biases the shift
    # by half a pixel: crop (centred) to even sizes that need no padding
    h, w = _dft_size(a.shape[0]), _dft_size(a.shape[1])
    r0, c0 = (a.shape[0] - h) // 2, (a.shape[1] - w) // 2
    a, b = a[r0:r0 + h, c0:c0 + w], b[r0:r0 + h, c0:c0 + w]
    window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_64F)
    (du, dv), response = cv2.phaseCorrelate(a - a.mean(), b - b.mean(), window)
    return BurstMotion((float(du), float(dv)), math.hypot(du, dv), min(float(response), 1.0))


def _dft_size(n: int) -> int:
    """The largest even size <= n that ``cv2.getOptimalDFTSize`` leaves as it is."""
    size = n // 2 * 2
    while size > 2 and cv2.getOptimalDFTSize(size) != size:
        size -= 2
    return size
