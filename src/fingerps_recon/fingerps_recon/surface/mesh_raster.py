"""A triangle mesh's per-node values sampled on a regular grid (barycentric interpolation).

Used by the unrolling's inverse map (:mod:`fingerps_recon.surface.surface_unrolling`: the
source pixel of each point of the print's grid) and by the rolled layout
(:mod:`fingerps_recon.surface.rolled_layout`: the surface's depth on its section grid). The
loop over the triangles is compiled: :func:`fingerps_recon.surface.print_kernel.rasterise`.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.surface import print_kernel


def rasterise_mesh(xy: np.ndarray, values: np.ndarray, triangles: np.ndarray, *,
                   origin: tuple[float, float], pitch: tuple[float, float],
                   shape: tuple[int, int]) -> np.ndarray:
    """Barycentric interpolation of ``values`` over ``triangles`` (T, 3) of the points ``xy``
    (N, 2), sampled at origin + (col, row) * pitch: (h, w, 2) float32 for values (N, 2),
    (h, w) for values (N,); NaN off the triangles."""
    one = np.ndim(values) == 1
    pairs = np.c_[values, values] if one else values
    out = np.full((*shape, 2), np.nan, dtype=np.float32)
    grid_xy = (np.asarray(xy, dtype=np.float64) - np.asarray(origin)) / np.asarray(pitch)
    print_kernel.rasterise(np.ascontiguousarray(grid_xy),
                           np.ascontiguousarray(pairs, dtype=np.float64),
                           np.ascontiguousarray(triangles, dtype=np.int64), out)
    return out[..., 0] if one else out
