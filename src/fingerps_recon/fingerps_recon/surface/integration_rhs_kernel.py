"""Compiled pass of the FAST solver (:mod:`surface.integration_fast`) that sets up its
equations, in one pass over the mask's bounding box (:func:`assemble_rhs`): each pixel's
steps from its normal (:func:`_steps_row`, the log-depth gradient of
:mod:`surface.integration`, dz~/du = nx / (fx D), dz~/dv = -(ny + s nx / fx) / (fy D), or
the orthographic slopes), the right-hand side b = D^T g of the masked Poisson equation
A h = D^T g, its moments and the mask's runs (maximal horizontal segments of mask pixels,
:func:`_row_runs`).

Inner loops run over whole rows without branches (selects), which LLVM vectorises; the
sums over pixels are kept per column. Runs on the calling thread (``serial_kernel``), cached
on disk as the other kernels; importing this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)
from fingerps_recon.surface.integration_sum_kernel import ordered_sum

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_HALF = np.float32(0.5)
_INF = np.float32(np.inf)


@inline_kernel
def _steps_row(normals, mask, r, c0, w, xs, yn, skew, min_nz, fx, fy, du_r, dv_r):
    """du_r, dv_r (w,) float32 (written): the steps of the pixels c0..c0 + w - 1 of image row
    r of ``normals`` (H, W, 3) float32 and ``mask`` (H, W) uint8; ``xs`` (w,) and ``yn``
    the pixels' rays' normalised coordinates (x_n with the skew taken out), ``skew`` =
    s / fx, ``min_nz``, ``fx``, ``fy`` (all float32):

    D = max(nz - nx x_n + ny y_n, min_nz |n| |r|), du = nx / (fx D),
    dv = -(ny + s nx / fx) / (fy D), both 0 where the pixel is outside the mask or its
    normal is zero or not finite. With x_n = y_n = 0 and fx = fy = -1 these are the
    orthographic slopes in pixels, du = -nx / D, dv = ny / D, D = max(nz, min_nz |n|).
    The row's normals are read as one flat run of 3 w floats (LLVM vectorises the
    interleaved loads)."""
    src = normals[r, c0:c0 + w].reshape(-1)
    inside = mask[r, c0:c0 + w]
    minus_ratio = -fx / fy
    yn2 = yn * yn + _F1
    for c in range(w):
        a, b, z, xn = src[3 * c], src[3 * c + 1], src[3 * c + 2], xs[c]
        norm2 = a * a + b * b + z * z
        usable = (inside[c] != 0) & (norm2 > _F0) & (norm2 < _INF)
        den = z - a * xn + b * yn
        low = min_nz * np.sqrt((xn * xn + yn2) * norm2)  # min_nz |r| |n|, one root
        den = den if den > low else low
        inv = _F1 / (den * fx)
        du_r[c] = a * inv if usable else _F0
        dv_r[c] = (b + skew * a) * minus_ratio * inv if usable else _F0


@inline_kernel
def _row_runs(row, w, flips, run_start, run_stop, n_runs):
    """Append the runs of ``row`` (w uint8) to run_start/run_stop from n_runs; returns the
    new count. ``flips`` (w + 1) uint8 scratch: where the row changes, read 32 at a time."""
    flips[0] = row[0]
    for c in range(1, w):
        flips[c] = row[c] ^ row[c - 1]
    flips[w] = row[w - 1]
    start = 0
    opened = False
    for block in range(0, w + 1, 32):
        stop = min(block + 32, w + 1)
        any_flip = np.uint8(0)
        for c in range(block, stop):
            any_flip |= flips[c]
        if any_flip:
            for c in range(block, stop):
                if flips[c]:
                    if opened:
                        run_start[n_runs] = start
                        run_stop[n_runs] = c
                        n_runs += 1
                    else:
                        start = c
                    opened = not opened
    return n_runs


@serial_kernel
def assemble_rhs(normals, mask, r0, c0, h, w, x_n, y_n, skew, min_nz, fx, fy, row_powers,
                 b, col_moments, run_start, run_stop, row_first):
    """b = D^T g over the box of h x w pixels from row r0, column c0, its moments and the
    mask's runs; returns (number of runs, |b|^2).

    The steps are those of :func:`_steps_row` (same arguments; ``x_n`` (1, w) or, with a
    skew, (h, w), ``y_n`` (h,)), computed row by row (two rows kept). ``b`` (h, w2)
    float32, w2 >= w (written; zero outside the mask and in the padding): g on each edge
    between 4-neighbours both in the mask is the mean of their two steps; a pixel gets +g
    from the edge before it (left, above) and -g from the one after. ``col_moments``
    (k, w) float64 (written): the sums over the rows of b[r, c] row_powers[r, j]
    (``row_powers`` (h, >= k) float64) - per column, so that the sums are element-wise.
    ``run_start``, ``run_stop`` (int32, room for every run): columns [start, stop) of each
    run, in raster order; ``row_first`` (h + 1,) int32: runs of row r are
    row_first[r]:row_first[r + 1]."""
    w2 = b.shape[1]
    n_mom = col_moments.shape[0]
    du = np.empty((2, w), dtype=np.float32)  # rows r, r + 1 (cyclic)
    dv = np.empty((2, w), dtype=np.float32)
    across = np.zeros(w + 1, dtype=np.float32)  # across[c + 1]: 2 g on edge (c, c + 1)
    above = np.zeros(w, dtype=np.float32)       # 2 g on the edges (r - 1, r)
    below = np.zeros(w, dtype=np.float32)       # 2 g on the edges (r, r + 1)
    flips = np.empty(w + 1, dtype=np.uint8)
    squares = np.zeros(w, dtype=np.float32)  # |b|^2 per column: a tolerance's scale
    col_moments[:] = 0.0
    n_runs = 0
    _steps_row(normals, mask, r0, c0, w, x_n[0], y_n[0], skew, min_nz, fx, fy, du[0], dv[0])
    for r in range(h):
        row = mask[r0 + r, c0:c0 + w]
        du_r = du[r % 2]
        dv_r = dv[r % 2]
        if r + 1 < h:
            dv_down = dv[(r + 1) % 2]
            _steps_row(normals, mask, r0 + r + 1, c0, w, x_n[r + 1 if x_n.shape[0] > 1 else 0],
                       y_n[r + 1], skew, min_nz, fx, fy, du[(r + 1) % 2], dv_down)
            down = mask[r0 + r + 1, c0:c0 + w]
            for c in range(w):
                below[c] = np.float32(row[c] & down[c]) * (dv_r[c] + dv_down[c])
        else:
            below[:] = _F0
        for c in range(w - 1):
            across[c + 1] = np.float32(row[c] & row[c + 1]) * (du_r[c] + du_r[c + 1])
        b_r = b[r]
        for c in range(w):
            value = _HALF * ((across[c] - across[c + 1]) + (above[c] - below[c]))
            b_r[c] = value
            squares[c] += value * value
        for c in range(w, w2):
            b_r[c] = _F0
        for j in range(n_mom):
            t = row_powers[r, j]
            moments = col_moments[j]
            for c in range(w):
                moments[c] += t * b_r[c]
        above, below = below, above
        row_first[r] = n_runs
        n_runs = _row_runs(row, w, flips, run_start, run_stop, n_runs)
    row_first[h] = n_runs
    return n_runs, ordered_sum(squares, 0, w)


# After an edit of the compile options or of a module whose kernels these inline, the cached
# kernels are compiled anew.
drop_stale_caches(globals())
