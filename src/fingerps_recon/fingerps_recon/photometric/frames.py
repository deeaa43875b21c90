"""Conversion between the camera optical frame (REP-103) and the photometric-stereo frame.

Optical frame: x right, y down, z forward. PS frame (DiLiGenT): x right, y up, z towards
the camera. The two differ by a rotation of 180 degrees about x: diag(1, -1, -1).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import DTypeLike

_FLIP = np.array([1.0, -1.0, -1.0])


def _flip_yz(vectors: np.ndarray, dtype: DTypeLike | None) -> np.ndarray:
    """``vectors * diag(1, -1, -1)`` as a new array of ``dtype`` (default: the type of the
    product with a float64 array, as ``vectors * _FLIP``), in one pass.

    A product broadcast over the last axis (length 3) runs numpy's inner loop 3 elements
    at a time; a C-contiguous (..., M, 3) array is multiplied row by row instead, with the
    flip repeated M times: far fewer inner-loop calls for an image of normals."""
    v = np.asarray(vectors)
    shape = np.broadcast_shapes(v.shape, _FLIP.shape)  # (..., 1) spreads to (..., 3), as *
    out = np.empty(shape, np.result_type(v, _FLIP) if dtype is None else dtype)
    # float32 in and out: a float32 product, the same values (times +-1 is exact)
    flip = _FLIP.astype(v.dtype) if v.dtype == out.dtype and v.dtype.kind == "f" else _FLIP
    if v.ndim >= 2 and v.shape == out.shape and v.flags.c_contiguous and v.size:
        row = 3 * v.shape[-2]
        np.multiply(v.reshape(-1, row), np.tile(flip, v.shape[-2]), out=out.reshape(-1, row),
                    casting="unsafe")
    else:
        np.multiply(v, flip, out=out, casting="unsafe")
    return out


def optical_to_ps(vectors: np.ndarray, *, dtype: DTypeLike | None = None) -> np.ndarray:
    """Return ``vectors`` (..., 3) given in the optical frame, expressed in the PS frame.

    ``dtype``: of the new array (e.g. ``np.float32`` to keep float32 normals float32, with
    the same values as the float64 product cast); default float64 (or wider, as
    ``vectors * np.array([1.0, -1.0, -1.0])``)."""
    return _flip_yz(vectors, dtype)


def ps_to_optical(vectors: np.ndarray, *, dtype: DTypeLike | None = None) -> np.ndarray:
    """Return ``vectors`` (..., 3) given in the PS frame, expressed in the optical frame.

    ``dtype``: as in :func:`optical_to_ps`."""
    return _flip_yz(vectors, dtype)
