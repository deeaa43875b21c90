"""Compiled (numba) loops of the rolled print (:mod:`surface.rolled_print`,
:mod:`surface.surface_unrolling`).

- :func:`ridge_laplacian`: minus the divergence of the normals' slope field by central
  differences, and the pixels whose 3x3 neighbourhood is valid, in one pass over the
  finger's box (numpy needs a dozen passes and temporaries for the same).
- :func:`rasterise`: barycentric interpolation of per-node values over a triangle mesh at
  the points of a regular grid, triangle by triangle over its bounding box.
- :func:`block_moments`: the per-block moments of the unrolling's local depth fit, in one
  pass over the surface's box (no padded float64 copies of the image).

All run on the calling thread (``serial_kernel``): a print is a few milliseconds of work,
and on a loaded machine helper threads (a multithreaded BLAS's) keep the caller waiting.
Compiled and cached as the photometric kernels are (:mod:`photometric.kernel_compile`),
warmed up with them (:func:`warm_up`, called by :mod:`photometric.kernel_warm_up`).
"""

from __future__ import annotations

import math

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)

# Barycentric coordinates down to -EPS count as inside (points on shared edges).
_EPS = 1e-9
# Triangles whose bounding box spans this many grid cells or more are left out of the
# inverse map (a mesh cell is ~2-5 cells of the coarse print grid; a fold's sliver would
# cost its box's area).
MAX_TRIANGLE_CELLS = 64


@inline_kernel
def _clamped(nz: float, min_nz: float) -> float:
    """max(nz, min_nz), NaN kept (as np.maximum)."""
    return min_nz if nz < min_nz else nz


@serial_kernel
def ridge_laplacian(normals: np.ndarray, valid: np.ndarray, min_nz: float, scale_x: float,
                    scale_y: float, signal: np.ndarray, keep: np.ndarray) -> None:
    """Ridge signal of the normals ``normals`` (h, w, 3) float32, PS frame (x right, y up):
    ``signal`` (h, w) float32 = -div(p, q) with p = -nx / nz, q = -ny / nz (nz clamped to
    ``min_nz``) by central differences, scaled by ``scale_x`` = 1 / (2 dx) and ``scale_y`` =
    1 / (2 dy) (image rows run down: dq/dy = -dq/drow); 0 on the outer ring and where
    ``keep`` is False. ``keep`` (h, w) bool: ``valid`` and its 8 neighbours inside the array
    valid (a 3x3 erosion, the array's outside counting as valid).

    Two passes: -p of every pixel; then row by row, -q and the erosion along the row of the
    next row (three rows kept), the erosion along the column and the differences."""
    h, w = valid.shape
    minus_q = np.empty((3, w), dtype=np.float32)  # rows r - 1, r, r + 1 (cyclic)
    across = np.empty((3, w), dtype=np.bool_)     # valid eroded along the row, same rows
    minus_p = np.empty((h, w), dtype=np.float32)
    for r in range(h):
        for c in range(w):
            nz = _clamped(normals[r, c, 2], min_nz)
            minus_p[r, c] = normals[r, c, 0] / nz
    for r in range(min(h, 1)):
        _row_prepare(normals, valid, r, min_nz, minus_q[r % 3], across[r % 3])
    for r in range(h):
        if r + 1 < h:
            _row_prepare(normals, valid, r + 1, min_nz, minus_q[(r + 1) % 3],
                         across[(r + 1) % 3])
        above, here, below = across[(r - 1) % 3], across[r % 3], across[(r + 1) % 3]
        inner_row = 0 < r < h - 1
        for c in range(w):
            ok = here[c] and (r == 0 or above[c]) and (r == h - 1 or below[c])
            keep[r, c] = ok
            value = np.float32(0.0)
            if ok and inner_row and 0 < c < w - 1:
                value = np.float32((minus_p[r, c + 1] - minus_p[r, c - 1]) * scale_x
                                   - (minus_q[(r + 1) % 3, c] - minus_q[(r - 1) % 3, c])
                                   * scale_y)
            signal[r, c] = value


@inline_kernel
def _row_prepare(normals: np.ndarray, valid: np.ndarray, r: int, min_nz: float,
                 minus_q: np.ndarray, across: np.ndarray) -> None:
    """Row ``r``'s -q and its validity eroded along the row (3 pixels)."""
    w = valid.shape[1]
    for c in range(w):
        minus_q[c] = normals[r, c, 1] / _clamped(normals[r, c, 2], min_nz)
        across[c] = (valid[r, c] and (c == 0 or valid[r, c - 1])
                     and (c == w - 1 or valid[r, c + 1]))


@serial_kernel
def rasterise(grid_xy: np.ndarray, values: np.ndarray, triangles: np.ndarray,
              out: np.ndarray) -> None:
    """Barycentric interpolation of ``values`` (N, 2) float64 over ``triangles`` (T, 3) of
    the points ``grid_xy`` (N, 2) float64 (node positions in grid units: column, row) at
    the grid points of ``out`` (h, w, 2) float32, which keeps its values elsewhere. A grid
    point covered by several triangles (a shared edge) takes the last one's value."""
    h, w = out.shape[0], out.shape[1]
    for t in range(triangles.shape[0]):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay = grid_xy[i0, 0], grid_xy[i0, 1]
        bx, by = grid_xy[i1, 0], grid_xy[i1, 1]
        cx, cy = grid_xy[i2, 0], grid_xy[i2, 1]
        c_lo = math.floor(min(ax, bx, cx)) + 1
        c_hi = math.floor(max(ax, bx, cx))
        r_lo = math.floor(min(ay, by, cy)) + 1
        r_hi = math.floor(max(ay, by, cy))
        if max(c_hi - c_lo, r_hi - r_lo) >= MAX_TRIANGLE_CELLS:
            continue
        v0x, v0y, v1x, v1y = bx - ax, by - ay, cx - ax, cy - ay
        den = v0x * v1y - v0y * v1x
        if not abs(den) > 1e-12:
            continue
        for row in range(max(r_lo, 0), min(r_hi + 1, h)):
            py = row - ay
            for col in range(max(c_lo, 0), min(c_hi + 1, w)):
                px = col - ax
                l1 = (px * v1y - py * v1x) / den
                l2 = (v0x * py - v0y * px) / den
                l0 = 1.0 - l1 - l2
                if l0 >= -_EPS and l1 >= -_EPS and l2 >= -_EPS:
                    for k in range(2):
                        out[row, col, k] = (l0 * values[i0, k] + l1 * values[i1, k]
                                            + l2 * values[i2, k])


@serial_kernel
def block_moments(depth: np.ndarray, valid: np.ndarray, z_ref_mm: float, powers: np.ndarray,
                  z_terms: int, mom: np.ndarray, zmom: np.ndarray) -> None:
    """Per block of ``step`` x ``step`` pixels (``step`` = len(powers)): ``mom[i, j, k, l]``
    = sum over the block's valid pixels of du^k dv^l, ``zmom[i, j, k, l]`` (k, l <
    ``z_terms``) the same of (1e3 depth - ``z_ref_mm``) du^k dv^l; du, dv the pixel's
    offsets from the block's centre along columns and rows (``powers[o, k]`` = offset o to
    the k). ``mom`` and ``zmom`` (gh, gw, P, P) float64 are zeroed first; pixels beyond the
    image count as invalid. Row by row: the sums along each block's part of the row, then
    their products with the row's powers."""
    h, w = valid.shape
    step, n = powers.shape
    gh, gw = mom.shape[0], mom.shape[1]
    mom[:] = 0.0
    zmom[:] = 0.0
    along = np.empty((gw, n))
    z_along = np.empty((gw, z_terms))
    for r in range(min(h, gh * step)):
        along[:] = 0.0
        z_along[:] = 0.0
        for c in range(min(w, gw * step)):
            if valid[r, c]:
                b, o = c // step, c % step
                z = 1e3 * np.float64(depth[r, c]) - z_ref_mm
                for k in range(n):
                    along[b, k] += powers[o, k]
                for k in range(z_terms):
                    z_along[b, k] += z * powers[o, k]
        i, o = r // step, r % step
        for b in range(gw):
            for k in range(n):
                for el in range(n):
                    mom[i, b, k, el] += along[b, k] * powers[o, el]
            for k in range(z_terms):
                for el in range(z_terms):
                    zmom[i, b, k, el] += z_along[b, k] * powers[o, el]


def warm_up() -> None:
    """Compile (or load) the kernels for the dtypes :mod:`surface.rolled_print` gives them."""
    normals = np.zeros((5, 5, 3), dtype=np.float32)
    normals[..., 2] = 1.0
    valid = np.ones((5, 5), dtype=bool)
    # The finger's box of the image (a strided view) or all of it (contiguous).
    for box in ((slice(0, 4), slice(0, 4)), (slice(0, 5), slice(0, 5))):
        shape = valid[box].shape
        ridge_laplacian(normals[box], valid[box], np.float32(0.1), np.float32(1.0),
                        np.float32(1.0), np.empty(shape, dtype=np.float32),
                        np.empty(shape, dtype=bool))
    depth = np.full((6, 6), 0.1, dtype=np.float32)
    powers = np.ones((3, 5))
    for box in ((slice(0, 4), slice(0, 5)), (slice(0, 6), slice(0, 6))):
        block_moments(depth[box], np.ones((6, 6), dtype=bool)[box], 100.0, powers, 3,
                      np.empty((2, 2, 5, 5)), np.empty((2, 2, 3, 3)))
    xy = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])
    rasterise(xy, xy.copy(), np.array([[0, 1, 2]], dtype=np.int64),
              np.full((4, 4, 2), np.nan, dtype=np.float32))


drop_stale_caches(globals())
