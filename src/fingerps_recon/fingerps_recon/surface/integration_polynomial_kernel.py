"""Compiled passes of the FAST solver's polynomial space
(:mod:`surface.integration_polynomials`): the monomials s^a t^b, 1 <= a + b <= ``POLY_DEGREE``,
in the box's coordinates s, t scaled to [-1, 1].

- :func:`poly_tables`: the coordinates' powers and the monomials' steps along the edges.
- :func:`poly_row`: a polynomial's values along a row (inlined by the passes that need it).
- :func:`subtract_poly_laplacian`: b - A q for the polynomial start q.
- :func:`column_moments`, :func:`outline_moments`: the moments V^T b of the right-hand side
  and V^T r of the residual on the outline, for the start V^T A V c = V^T b and the last
  correction V^T A V c = V^T r; :func:`spd_inverse`, the Gram matrix's inverse.

Inner loops run over whole rows without branches, which LLVM vectorises; the sums over
pixels are kept per column. Run on the calling thread (``serial_kernel``), cached on disk
as the other kernels; importing this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)
from fingerps_recon.surface.integration_sum_kernel import ordered_sum

#: Degree of the polynomials the kernels evaluate (six coefficients per row).
POLY_DEGREE = 5


@inline_kernel
def _powers(x, out):
    """out[k] = x^k, k = 0 .. len(out) - 1, by repeated multiplication."""
    value = 1.0
    for k in range(out.shape[0]):
        out[k] = value
        value *= x


@serial_kernel
def poly_tables(col_powers, row_powers, pair_prefix, power_prefix, row_steps):
    """The polynomial space's tables for a box of h x w pixels (written; shapes give h, w
    and d): s(c) = (c - (w - 1) / 2) / ((w - 1) / 2) and t(r) likewise (1 for the
    divisor when it would be below 1); ``col_powers`` (d + 1, w) s(c)^a; ``row_powers``
    (h, 2 d + 1) t(r)^k; ``pair_prefix`` (w, d * d) and ``power_prefix``
    (w + 1, 2 d + 1), ``row_steps`` (h - 1, d * d) as
    :func:`surface.integration_topology_kernel.run_topology` reads them."""
    d = col_powers.shape[0] - 1
    h, n_powers = row_powers.shape
    w = col_powers.shape[1]
    half_w = max((w - 1) / 2, 1.0)
    half_h = max((h - 1) / 2, 1.0)
    s_powers = np.empty((w, n_powers))
    for c in range(w):
        _powers((c - (w - 1) / 2) / half_w, s_powers[c])
        for k in range(d + 1):
            col_powers[k, c] = s_powers[c, k]
    for r in range(h):
        _powers((r - (h - 1) / 2) / half_h, row_powers[r])
    pair_prefix[0, :] = 0.0
    for c in range(w - 1):
        for a in range(d):
            step_a = s_powers[c + 1, a + 1] - s_powers[c, a + 1]
            for a2 in range(d):
                step_a2 = s_powers[c + 1, a2 + 1] - s_powers[c, a2 + 1]
                pair_prefix[c + 1, a * d + a2] = pair_prefix[c, a * d + a2] + step_a * step_a2
    power_prefix[0, :] = 0.0
    for c in range(w):
        for k in range(n_powers):
            power_prefix[c + 1, k] = power_prefix[c, k] + s_powers[c, k]
    for r in range(h - 1):
        for b in range(d):
            step_b = row_powers[r + 1, b + 1] - row_powers[r, b + 1]
            for b2 in range(d):
                step_b2 = row_powers[r + 1, b2 + 1] - row_powers[r, b2 + 1]
                row_steps[r, b * d + b2] = step_b * step_b2


@inline_kernel
def poly_row(coef, row_powers, s, r, out, w):
    """out[:w] = q(r, c) = sum over a, b of coef[a, b] s[c]^a t(r)^b (float64; a, b <=
    POLY_DEGREE; ``row_powers`` (h, >= POLY_DEGREE + 1) t(r)^b): the row's coefficients in
    s first, then Horner along the row."""
    k0 = k1 = k2 = k3 = k4 = k5 = 0.0
    for b in range(POLY_DEGREE + 1):
        t = row_powers[r, b]
        k0 += coef[0, b] * t
        k1 += coef[1, b] * t
        k2 += coef[2, b] * t
        k3 += coef[3, b] * t
        k4 += coef[4, b] * t
        k5 += coef[5, b] * t
    for c in range(w):
        x = s[c]
        out[c] = ((((k5 * x + k4) * x + k3) * x + k2) * x + k1) * x + k0


@serial_kernel
def subtract_poly_laplacian(b, mask, r0, c0, h, w, coef, row_powers, s):
    """b[:h, :w] -= A q, A the masked graph Laplacian of the box of h x w pixels from row
    r0, column c0 of ``mask`` (H, W) uint8, q the polynomial of :func:`poly_row`
    (``coef`` (POLY_DEGREE + 1, POLY_DEGREE + 1) float64, s (w,) the columns'
    coordinate); returns the new |b|^2. A q = D^T (D q): the same sum over edges as b,
    with the step of q along each edge."""
    across = np.zeros(w + 1, dtype=np.float64)
    above = np.zeros(w, dtype=np.float64)
    below = np.zeros(w, dtype=np.float64)
    q = np.empty(w, dtype=np.float64)
    q_down = np.empty(w, dtype=np.float64)
    squares = np.zeros(w, dtype=np.float64)
    if h > 0:
        poly_row(coef, row_powers, s, 0, q_down, w)
    for r in range(h):
        q, q_down = q_down, q
        row = mask[r0 + r, c0:c0 + w]
        if r + 1 < h:
            poly_row(coef, row_powers, s, r + 1, q_down, w)
            down = mask[r0 + r + 1, c0:c0 + w]
            for c in range(w):
                below[c] = float(row[c] & down[c]) * (q_down[c] - q[c])
        else:
            below[:] = 0.0
        for c in range(w - 1):
            across[c + 1] = float(row[c] & row[c + 1]) * (q[c + 1] - q[c])
        b_r = b[r]
        for c in range(w):
            value = np.float32(b_r[c] - ((across[c] - across[c + 1]) + (above[c] - below[c])))
            b_r[c] = value
            squares[c] += float(value) * float(value)
        above, below = below, above
    return ordered_sum(squares, 0, w)


@serial_kernel
def column_moments(col_moments, col_powers, basis_a, basis_b, out):
    """out[i] = sum over c of col_moments[basis_b[i], c] col_powers[basis_a[i], c]: the
    moments of b (:func:`surface.integration_rhs_kernel.assemble_rhs`) against the
    monomials s^a t^b."""
    w = col_moments.shape[1]
    for i in range(basis_a.size):
        m = col_moments[basis_b[i]]
        p = col_powers[basis_a[i]]
        total = 0.0
        for c in range(w):
            total += m[c] * p[c]
        out[i] = total


@serial_kernel
def outline_moments(residual, rows, cols, n, row_powers, col_powers, basis_a, basis_b,
                    out):
    """out[i] = sum over the first n outline pixels of residual t(row)^b s(col)^a, with
    a = basis_a[i], b = basis_b[i] (``row_powers`` (h, >= d + 1), ``col_powers``
    (d + 1, w) float64): the moments of the residual against the monomials."""
    out[:] = 0.0
    for p in range(n):
        value = float(residual[p])
        r, c = rows[p], cols[p]
        for i in range(basis_a.size):
            out[i] += value * row_powers[r, basis_b[i]] * col_powers[basis_a[i], c]


@serial_kernel
def spd_inverse(a, out):
    """out = a^-1 for a symmetric positive definite (n, n) float64 ``a`` by its Cholesky
    factor; returns False (out unspecified) if a pivot is not above 1e-12 of the largest
    diagonal element (singular or indefinite by round-off)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    scale = 0.0
    for i in range(n):
        scale = max(scale, a[i, i])
    for j in range(n):
        pivot = a[j, j]
        for k in range(j):
            pivot -= low[j, k] * low[j, k]
        if not pivot > 1e-12 * scale:
            return False
        low[j, j] = np.sqrt(pivot)
        for i in range(j + 1, n):
            value = a[i, j]
            for k in range(j):
                value -= low[i, k] * low[j, k]
            low[i, j] = value / low[j, j]
    inv_low = np.zeros((n, n))  # L^-1, lower triangular
    for j in range(n):
        inv_low[j, j] = 1.0 / low[j, j]
        for i in range(j + 1, n):
            value = 0.0
            for k in range(j, i):
                value -= low[i, k] * inv_low[k, j]
            inv_low[i, j] = value / low[i, i]
    for i in range(n):  # a^-1 = L^-T L^-1
        for j in range(n):
            value = 0.0
            for k in range(max(i, j), n):
                value += inv_low[k, i] * inv_low[k, j]
            out[i, j] = value
    return True


# After an edit of the compile options or of a module whose kernels these inline, the cached
# kernels are compiled anew.
drop_stale_caches(globals())
