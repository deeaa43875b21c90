"""Normals as a colour picture: the usual (n + 1) / 2 mapping of the PS frame to RGB."""

from __future__ import annotations

import numpy as np


def normal_map_rgb(normals_ps: np.ndarray, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Return an (H, W, 3) uint8 RGB picture of unit normals (H, W, 3); black outside mask."""
    n = np.asarray(normals_ps, dtype=np.float32)
    rgb = np.clip((n + 1.0) * 127.5, 0.0, 255.0).astype(np.uint8)
    if mask is not None:
        rgb[~np.asarray(mask, dtype=bool)] = 0
    return rgb
