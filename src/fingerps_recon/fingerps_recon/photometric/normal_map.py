"""Normals as a colour picture: the usual (n + 1) / 2 mapping of the PS frame to RGB."""

from __future__ import annotations

import numpy as np


def normal_map_rgb(normals_ps: np.ndarray, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Return an (H, W, 3) uint8 RGB picture of unit normals (H, W, 3); black outside mask.

    Each channel is ``uint8(clip((n + 1) * 127.5, 0, 255))`` computed in float32 (values
    above 255 or below 0 saturate; the cast truncates)."""
    n = np.asarray(normals_ps, dtype=np.float32)
    scaled = np.add(n, np.float32(1.0))  # a new array: the passes below work in place
    scaled *= np.float32(127.5)
    np.clip(scaled, 0.0, 255.0, out=scaled)
    rgb = scaled.astype(np.uint8, order="C")
    if mask is None:
        return rgb
    inside = np.asarray(mask, dtype=bool)
    if inside.shape == rgb.shape[:-1]:
        # Multiplying by the mask repeated per channel: one pass with long inner loops
        # (boolean indexing of (H, W, 3) by an (H, W) mask is ~10x slower).
        flat = rgb.reshape(-1)
        flat *= np.repeat(inside.reshape(-1), rgb.shape[-1])
    else:
        rgb[~inside] = 0
    return rgb
