"""Analytic surfaces whose normals the tests know exactly.

``sphere_normals``: an orthographic sphere centred in the image, in the PS frame (x right,
y up, z towards the camera), the reference input of the Lambertian, many-light and offline
reconstruction tests.
"""

from __future__ import annotations

import numpy as np


def sphere_normals(height: int, width: int, *, radius_px: float,
                   within: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) of a sphere of ``radius_px`` centred in an H x W image, its mask
    (x^2 + y^2 < ``within`` in radii: 0.9 is a cap out to 72 degrees) and its height (H, W) in
    pixels; normals are 0 outside the mask."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = (u - (width - 1) / 2) / radius_px, -(v - (height - 1) / 2) / radius_px
    r2 = x * x + y * y
    mask = r2 < within
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normals = np.where(mask[..., None], np.stack([x, y, z], axis=-1), 0.0)
    return normals, mask, z * radius_px
