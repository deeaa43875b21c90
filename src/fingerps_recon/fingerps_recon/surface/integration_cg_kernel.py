"""Compiled passes of one conjugate-gradient step of the FAST solver
(:mod:`surface.integration_fast`).

After the first step the residual is zero but on the outline pixels (the mask pixels with a
4-neighbour in the DCT box but outside the mask), so only the dense update of the solution
and the direction passes over the whole box (:func:`take_direction`); the scalar products,
A d and the residual's update run over the outline pixels alone (:func:`outline_dot`,
:func:`outline_laplacian`, :func:`outline_update`), and so does the DCT-II along the rows of
the next preconditioner input (:func:`outline_spectrum`). :func:`neumann_columns` is the
preconditioner's tridiagonal solve down the columns, between its DCTs
(:mod:`surface.integration_preconditioner`).

Run on the calling thread (``serial_kernel``), cached on disk as the other kernels;
importing this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import drop_stale_caches, serial_kernel
from fingerps_recon.surface.integration_sum_kernel import ordered_sum

_F0 = np.float32(0.0)


@serial_kernel
def take_direction(z, mask, r0, c0, x, d, alpha, beta, step):
    """The dense part of a conjugate-gradient step, one pass over the box of x's shape
    (h, w) from row r0, column c0 of ``mask`` (H, W) uint8, with ``z`` (h, w2) float32 on
    the mask pixels (0 elsewhere): step 0, d = z (x is not read nor written); step 1,
    x = alpha d (the first step's), then d = z + beta d; later steps x += alpha d, then
    d = z + beta d. ``x``, ``d`` (h, w) float32; ``alpha``, ``beta`` float32. Returns the
    sum of the new d (float64; d is zero outside the mask), kept per column."""
    h, w = x.shape
    sums = np.zeros(w, dtype=np.float64)
    for r in range(h):
        inside = mask[r0 + r, c0:c0 + w]
        z_r = z[r]
        x_r = x[r]
        d_r = d[r]
        if step == 0:
            for c in range(w):
                value = z_r[c] * np.float32(inside[c])
                d_r[c] = value
                sums[c] += value
        elif step == 1:
            for c in range(w):
                x_r[c] = alpha * d_r[c]
                value = z_r[c] * np.float32(inside[c]) + beta * d_r[c]
                d_r[c] = value
                sums[c] += value
        else:
            for c in range(w):
                x_r[c] += alpha * d_r[c]
                value = z_r[c] * np.float32(inside[c]) + beta * d_r[c]
                d_r[c] = value
                sums[c] += value
    return ordered_sum(sums, 0, w)


@serial_kernel
def outline_dot(buf, rows, cols, n, values):
    """sum over the first n outline pixels of values[i] * buf[rows[i], cols[i]]."""
    total = 0.0
    for i in range(n):
        total += float(values[i]) * float(buf[rows[i], cols[i]])
    return total


@serial_kernel
def outline_laplacian(d, mask, r0, c0, rows, cols, n, out):
    """out[i] = (A d) at outline pixel i (masked graph Laplacian of the box's mask, d zero
    outside it); returns sum of d * A d over them (float64)."""
    h, w = d.shape
    total = 0.0
    for i in range(n):
        r, c = rows[i], cols[i]
        here = d[r, c]
        acc = _F0
        if c > 0 and mask[r0 + r, c0 + c - 1]:
            acc += here - d[r, c - 1]
        if c + 1 < w and mask[r0 + r, c0 + c + 1]:
            acc += here - d[r, c + 1]
        if r > 0 and mask[r0 + r - 1, c0 + c]:
            acc += here - d[r - 1, c]
        if r + 1 < h and mask[r0 + r + 1, c0 + c]:
            acc += here - d[r + 1, c]
        out[i] = acc
        total += float(here) * float(acc)
    return total


@serial_kernel
def outline_update(residual, product, alpha, n):
    """residual -= alpha product on the first n outline pixels; returns the residual's
    squared norm (float64)."""
    total = 0.0
    for i in range(n):
        value = residual[i] - alpha * product[i]
        residual[i] = value
        total += float(value) * float(value)
    return total


@serial_kernel
def outline_spectrum(residual, spec, rows, cols, n, cosines):
    """``spec`` (h, w2) float32 (written): the DCT-II along the rows of the residual on the
    first n outline pixels (zero elsewhere) - the outline pixels' rows of
    ``cosines`` (w2, w2) float32 (cosines[c, j]: the orthonormal DCT-II's coefficient of
    column c in frequency j) scaled by their residual: a few pixels a row, cheaper than
    transforming the whole rows. Rows without outline pixels are zeroed."""
    h = spec.shape[0]
    done = 0  # rows before this one are written
    for i in range(n):
        r = rows[i]
        out = spec[r]
        basis = cosines[cols[i]]
        value = residual[i]
        if r >= done:
            for skipped in range(done, r):
                spec[skipped] = _F0
            for j in range(out.size):
                out[j] = value * basis[j]
            done = r + 1
        else:
            for j in range(out.size):
                out[j] += value * basis[j]
    for skipped in range(done, h):
        spec[skipped] = _F0


@serial_kernel
def neumann_columns(spec, inv_pivot, inv_last):
    """Solve (T + mu_k I) y = f in place for every column k of ``spec`` (h, w2) float32, T
    the h x h Neumann second difference (1, 2, ..., 2, 1 on the diagonal, -1 beside it) and
    mu_k = 2 - 2 cos(pi k / w2): the box's Laplacian once the rows are in the DCT-II basis.

    Thomas' algorithm: d_i = (f_i + d_{i-1}) / p_i down the rows, y_i = d_i + y_{i+1} / p_i
    up again, row by row across all columns (vectorised); 1 / p_i from ``inv_pivot``
    (>= h - 1, w2) float32 for rows 0..h-2 and ``inv_last`` (w2,) float32 for row h - 1.
    Column 0 (mu = 0, T singular) gets the pseudo-inverse instead, the solution of zero mean
    (the box's constant is free), from the running sums of f (float64)."""
    h, w = spec.shape
    # column 0: y_i - y_{i+1} = f_0 + ... + f_i, f less its mean, then y less its mean
    mean = 0.0
    for i in range(h):
        mean += spec[i, 0]
    mean /= h
    flux = 0.0
    y = 0.0
    total = 0.0
    col = np.empty(h, dtype=np.float64)
    for i in range(h):
        col[i] = y
        total += y
        flux += spec[i, 0] - mean
        y -= flux
    shift = total / h
    row = spec[0]
    inv = inv_pivot[0] if h > 1 else inv_last
    for c in range(w):
        row[c] *= inv[c]
    for i in range(1, h):
        row, above = spec[i], spec[i - 1]
        inv = inv_pivot[i] if i < h - 1 else inv_last
        for c in range(w):
            row[c] = (row[c] + above[c]) * inv[c]
    for i in range(h - 2, -1, -1):
        row, below = spec[i], spec[i + 1]
        inv = inv_pivot[i]
        for c in range(w):
            row[c] += inv[c] * below[c]
    for i in range(h):
        spec[i, 0] = np.float32(col[i] - shift)


# After an edit of the compile options or of a module whose kernels these inline, the cached
# kernels are compiled anew.
drop_stale_caches(globals())
