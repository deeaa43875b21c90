"""The bounding box of a mask: the rectangle the per-pixel steps work on.

Photometric stereo (Lambertian), the ridge enhancement (Eq. 12) and the integration solve
only inside the smallest rectangle holding every mask pixel; outside it the results are
zero or NaN without computing them.
"""

from __future__ import annotations

import numpy as np


def mask_bounding_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """Slices (rows, columns) of the smallest rectangle holding every mask pixel.

    Parameters
    ----------
    mask : (H, W) bool

    Returns
    -------
    tuple of two slices, or None
        ``mask[box]`` holds every True pixel; None for an empty mask.
    """
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0] : rows[-1] + 1].any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)
