"""Conversion between the camera optical frame (REP-103) and the photometric-stereo frame.

Optical frame: x right, y down, z forward. PS frame (DiLiGenT): x right, y up, z towards
the camera. The two differ by a rotation of 180 degrees about x: diag(1, -1, -1).
"""

from __future__ import annotations

import numpy as np

_FLIP = np.array([1.0, -1.0, -1.0])


def optical_to_ps(vectors: np.ndarray) -> np.ndarray:
    """Return ``vectors`` (..., 3) given in the optical frame, expressed in the PS frame."""
    return np.asarray(vectors) * _FLIP


def ps_to_optical(vectors: np.ndarray) -> np.ndarray:
    """Return ``vectors`` (..., 3) given in the PS frame, expressed in the optical frame."""
    return np.asarray(vectors) * _FLIP
