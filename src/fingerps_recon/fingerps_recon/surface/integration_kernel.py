"""Compiled (numba) loops of the FAST solver of :mod:`surface.integration`, whose module
docstring says what is computed and why.

- :func:`assemble_rhs`: each pixel's steps from its normal (:func:`_steps_row`), the
  right-hand side b = D^T g, its moments and the mask's runs (maximal horizontal segments),
  in one pass over the box.
- :func:`run_topology`: from the runs alone, the 4-connected components (union-find), the
  outline pixels (mask pixels with a 4-neighbour in the DCT box but outside the mask) and
  the Gram matrix V^T A V of the polynomial space; :func:`poly_tables` its tables.
- :func:`subtract_poly_laplacian`: b - A q for the polynomial start q.
- one conjugate-gradient step: :func:`take_direction` (the dense part, one pass),
  :func:`outline_dot`, :func:`outline_laplacian`, :func:`outline_update`,
  :func:`outline_spectrum` (on the outline pixels only, where the residual lives);
  :func:`neumann_columns`, the preconditioner's tridiagonal solves between its DCTs.
- :func:`column_moments`, :func:`outline_moments`, :func:`spd_inverse`: the polynomial
  start and correction.
- :func:`write_solution`, :func:`finish_runs`: the solution into the caller's output, each
  component's mean taken out, exponentiated for a depth.

Inner loops run over whole rows without branches (selects), which LLVM vectorises; loops
over runs are not vectorised, so rows are computed whole and then patched. IEEE arithmetic
forbids LLVM to reorder a sum (:mod:`photometric.kernel_compile`), so sums over pixels are
either kept per column (element-wise) or split into eight partial sums. All run on the
calling thread (``serial_kernel``) and are cached on disk as the other kernels. Importing
this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)

#: Degree of the polynomials the kernels evaluate (six coefficients per row).
POLY_DEGREE = 5

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
def _sum(values, start, stop):
    """sum(values[start:stop]) in float64, eight partial sums (independent chains)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    c = start
    while c + 8 <= stop:
        s0 += values[c]
        s1 += values[c + 1]
        s2 += values[c + 2]
        s3 += values[c + 3]
        s4 += values[c + 4]
        s5 += values[c + 5]
        s6 += values[c + 6]
        s7 += values[c + 7]
        c += 8
    while c < stop:
        s0 += values[c]
        c += 1
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


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
def _find(parent, i):
    """Root of run i (union-find), compressing the path."""
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@serial_kernel
def _clip_segments(src_lo, src_hi, n_seg, run_start, run_stop, first, last, dst_lo, dst_hi):
    """dst = the segments src[:n_seg] (sorted, disjoint) clipped to the runs first:last of
    another row (sorted, disjoint); returns their number."""
    out = 0
    k = first
    for i in range(n_seg):
        a, z = src_lo[i], src_hi[i]
        while k < last and run_stop[k] <= a:
            k += 1
        j = k
        while j < last and run_start[j] < z:
            s = max(a, run_start[j])
            e = min(z, run_stop[j])
            if s < e:
                dst_lo[out] = s
                dst_hi[out] = e
                out += 1
            j += 1
    return out


@serial_kernel
def run_topology(run_start, run_stop, row_first, w2, pair_prefix, power_prefix, row_powers,
                 row_steps, basis_a, basis_b, labels, outline_rows, outline_cols, gram,
                 mask_moments, seg_lo, seg_hi):
    """Components, outline pixels and the polynomial space's Gram matrix, from the runs.

    ``run_start``, ``run_stop``, ``row_first`` as written by :func:`assemble_rhs` for a box
    of h = row_first.size - 1 rows and w columns, in a DCT box of h x ``w2`` (w2 >= w: the
    columns from w on are outside the mask).
    Monomials s^a t^b (a = ``basis_a[i]``, b = ``basis_b[i]``, 1 <= a + b <= d) in the
    coordinates s(c), t(r) of :func:`integration._poly_tables`, whose tables are:
    ``pair_prefix`` (w, d * d) float64, pair_prefix[c, (a - 1) d + a' - 1] = sum over
    c' < c of Dh_a(c') Dh_a'(c') with Dh_a(c) = s(c + 1)^a - s(c)^a; ``power_prefix``
    (w + 1, 2 d + 1) float64, power_prefix[c, k] = sum over c' < c of s(c')^k;
    ``row_powers`` (h, 2 d + 1) float64, t(r)^k; ``row_steps`` (h - 1, d * d) float64,
    Dv_b(r) Dv_b'(r) (flat as pair_prefix) with Dv_b(r) = t(r + 1)^b - t(r)^b.

    Written: ``labels`` (n_runs,) int32 component of each run (0..n_comp - 1, in order of
    first appearance); ``outline_rows``, ``outline_cols`` int32 (room for every mask pixel):
    the mask pixels with a 4-neighbour inside the DCT box but outside the mask, row by row;
    ``gram`` (n, n) float64: V^T A V, the sum over the mask's edges of the products of the
    monomials' steps along them - per row, (Dh_a t^b)(Dh_a' t^b') over its horizontal edges
    and (s^a Dv_b)(s^a' Dv_b') over the vertical edges to the next row, from the prefix sums;
    ``mask_moments`` (d + 1, d + 1) float64: the sums over the mask of s^a t^b [a, b].
    ``seg_lo``, ``seg_hi`` (2, >= w + 1) int32 scratch. Returns (number of components,
    number of outline pixels)."""
    h = row_first.size - 1
    n_runs = row_first[h]
    parent = np.arange(n_runs, dtype=np.int32)
    d = basis_a.max() if basis_a.size else 0
    dd = d * d
    n_powers = power_prefix.shape[1]
    # sum over rows of t^k (sum over the row's horizontal edges of Dh_a Dh_a'), flat (a, a')
    across = np.zeros((n_powers, dd))
    # sum over pairs of rows of Dv_b Dv_b' (sum over their vertical edges of s^k), flat (b, b')
    along = np.zeros((n_powers, dd))
    pairs = np.empty(dd)
    powers = np.empty(n_powers)
    mask_moments[:] = 0.0
    n_out = 0
    for r in range(h):
        first, last = row_first[r], row_first[r + 1]
        if first < last:
            pairs[:] = 0.0
            for i in range(first, last):
                c0, c1 = run_start[i], run_stop[i]
                if c1 - c0 > 1:  # horizontal edges c0..c1 - 2
                    high, low = pair_prefix[c1 - 1], pair_prefix[c0]
                    for m in range(dd):
                        pairs[m] += high[m] - low[m]
                for a in range(d + 1):
                    run_sum = power_prefix[c1, a] - power_prefix[c0, a]
                    for b in range(d + 1):
                        mask_moments[a, b] += run_sum * row_powers[r, b]
            for k in range(n_powers):
                t = row_powers[r, k]
                acc = across[k]
                for m in range(dd):
                    acc[m] += t * pairs[m]
        if r > 0 and first < last:  # vertical edges to the row above: overlaps; unions
            up_first, up_last = row_first[r - 1], row_first[r]
            powers[:] = 0.0
            k = up_first
            for i in range(first, last):
                c0, c1 = run_start[i], run_stop[i]
                while k < up_last and run_stop[k] <= c0:
                    k += 1
                j = k
                while j < up_last and run_start[j] < c1:
                    s = max(c0, run_start[j])
                    e = min(c1, run_stop[j])
                    if s < e:
                        for p in range(n_powers):
                            powers[p] += power_prefix[e, p] - power_prefix[s, p]
                        ra = _find(parent, i)
                        rb = _find(parent, j)
                        if ra != rb:
                            if ra < rb:
                                parent[rb] = ra
                            else:
                                parent[ra] = rb
                    j += 1
            steps = row_steps[r - 1]
            for p in range(n_powers):
                acc = along[p]
                weight = powers[p]
                for m in range(dd):
                    acc[m] += weight * steps[m]
        # Outline: each run less its inner part, the pixels whose four neighbours in the
        # DCT box are all mask pixels (a missing neighbour - the box's edge - is no edge).
        up_first = row_first[r - 1] if r > 0 else -1
        up_last = row_first[r] if r > 0 else -1
        if r + 1 < h:
            down_first, down_last = row_first[r + 1], row_first[r + 2]
        else:
            down_first, down_last = -1, -1  # the DCT box's edge
        for i in range(first, last):
            c0, c1 = run_start[i], run_stop[i]
            lo = c0 + 1 if c0 > 0 else c0
            hi = c1 - 1 if c1 < w2 else c1
            n_seg = 0
            if lo < hi:
                seg_lo[0, 0] = lo
                seg_hi[0, 0] = hi
                n_seg = 1
            now = 0
            if up_first >= 0:
                n_seg = _clip_segments(seg_lo[now], seg_hi[now], n_seg, run_start, run_stop,
                                       up_first, up_last, seg_lo[1 - now], seg_hi[1 - now])
                now = 1 - now
            if down_first >= 0:
                n_seg = _clip_segments(seg_lo[now], seg_hi[now], n_seg, run_start, run_stop,
                                       down_first, down_last, seg_lo[1 - now],
                                       seg_hi[1 - now])
                now = 1 - now
            cursor = c0
            for k2 in range(n_seg + 1):
                stop = seg_lo[now, k2] if k2 < n_seg else c1
                for c in range(cursor, stop):
                    outline_rows[n_out] = r
                    outline_cols[n_out] = c
                    n_out += 1
                if k2 < n_seg:
                    cursor = seg_hi[now, k2]
    n_comp = 0
    for i in range(n_runs):
        root = _find(parent, i)
        if root == i:
            labels[i] = n_comp
            n_comp += 1
        else:
            labels[i] = labels[root]  # root < i: labelled already
    for i in range(basis_a.size):
        a, b = basis_a[i], basis_b[i]
        for j in range(basis_a.size):
            a2, b2 = basis_a[j], basis_b[j]
            value = 0.0
            if a > 0 and a2 > 0:
                value += across[b + b2, (a - 1) * d + a2 - 1]
            if b > 0 and b2 > 0:
                value += along[a + a2, (b - 1) * d + b2 - 1]
            gram[i, j] = value
    return n_comp, n_out


@serial_kernel
def poly_tables(col_powers, row_powers, pair_prefix, power_prefix, row_steps):
    """The polynomial space's tables for a box of h x w pixels (written; shapes give h, w
    and d): s(c) = (c - (w - 1) / 2) / ((w - 1) / 2) and t(r) likewise (1 for the
    divisor when it would be below 1); ``col_powers`` (d + 1, w) s(c)^a; ``row_powers``
    (h, 2 d + 1) t(r)^k; ``pair_prefix`` (w, d * d) and ``power_prefix``
    (w + 1, 2 d + 1), ``row_steps`` (h - 1, d * d) as :func:`run_topology` reads them."""
    d = col_powers.shape[0] - 1
    h, n_powers = row_powers.shape
    w = col_powers.shape[1]
    half_w = max((w - 1) / 2, 1.0)
    half_h = max((h - 1) / 2, 1.0)
    s_powers = np.empty((w, n_powers))
    for c in range(w):
        s = (c - (w - 1) / 2) / half_w
        value = 1.0
        for k in range(n_powers):
            s_powers[c, k] = value
            value *= s
        for k in range(d + 1):
            col_powers[k, c] = s_powers[c, k]
    for r in range(h):
        t = (r - (h - 1) / 2) / half_h
        value = 1.0
        for k in range(n_powers):
            row_powers[r, k] = value
            value *= t
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


@serial_kernel
def column_moments(col_moments, col_powers, basis_a, basis_b, out):
    """out[i] = sum over c of col_moments[basis_b[i], c] col_powers[basis_a[i], c]: the
    moments of b (:func:`assemble_rhs`) against the monomials s^a t^b."""
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
    return n_runs, _sum(squares, 0, w)


@inline_kernel
def _poly_row(coef, row_powers, s, r, out, w):
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
    r0, column c0 of ``mask`` (H, W) uint8, q the polynomial of :func:`_poly_row`
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
        _poly_row(coef, row_powers, s, 0, q_down, w)
    for r in range(h):
        q, q_down = q_down, q
        row = mask[r0 + r, c0:c0 + w]
        if r + 1 < h:
            _poly_row(coef, row_powers, s, r + 1, q_down, w)
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
    return _sum(squares, 0, w)


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
    return _sum(sums, 0, w)


# Taylor coefficients 1 / k! of exp, k = 8..1, for Horner on |t| <= _EXP_REACH: the
# remainder t^9 / 9! is below 2.2e-10 of exp(t); 2^m-fold squaring multiplies that by 2^m.
# On |t| <= _EXP_NEAR (a finger's depths within +-5 % of their mean) the terms to t^5 do as
# well: the remainder t^6 / 6! is below 2.2e-11.
_EXP_TAYLOR = np.array([1.0 / 40320, 1.0 / 5040, 1.0 / 720, 1.0 / 120, 1.0 / 24, 1.0 / 6,
                        0.5, 1.0])
_EXP_REACH = 0.35
_EXP_NEAR = 0.05


@inline_kernel
def _larger(best, value, center):
    """|value - center| if that is larger than ``best`` (a NaN value is not), else best."""
    deviation = abs(value - center)
    return deviation if deviation > best else best


@inline_kernel
def _max_deviation(values, start, stop, center):
    """max |values[start:stop] - center| (float64; NaN ignored), eight partial maxima."""
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = 0.0
    c = start
    while c + 8 <= stop:
        m0 = _larger(m0, values[c], center)
        m1 = _larger(m1, values[c + 1], center)
        m2 = _larger(m2, values[c + 2], center)
        m3 = _larger(m3, values[c + 3], center)
        m4 = _larger(m4, values[c + 4], center)
        m5 = _larger(m5, values[c + 5], center)
        m6 = _larger(m6, values[c + 6], center)
        m7 = _larger(m7, values[c + 7], center)
        c += 8
    while c < stop:
        m0 = _larger(m0, values[c], center)
        c += 1
    return max(max(max(m0, m1), max(m2, m3)), max(max(m4, m5), max(m6, m7)))


@inline_kernel
def _exp_span(src, dst, start, stop, center, scale, factor, reach, work):
    """dst[start:stop] = factor exp(scale (src - center)) in float64, rounded once to
    float32: with t the exponent divided by 2^m so that |t| <= _EXP_REACH (m from
    ``reach``, a bound of |scale (src - center)|), the Taylor polynomial of exp(t) squared
    m times (to t^5 only when ``reach`` <= _EXP_NEAR). ``work`` float64 scratch of the
    row's length."""
    k3, k4, k5, k6, k7 = (_EXP_TAYLOR[3], _EXP_TAYLOR[4], _EXP_TAYLOR[5], _EXP_TAYLOR[6],
                          _EXP_TAYLOR[7])
    if reach <= _EXP_NEAR:
        for c in range(start, stop):
            t = scale * (src[c] - center)
            work[c] = ((((k3 * t + k4) * t + k5) * t + k6) * t + k7) * t + 1.0
        for c in range(start, stop):
            dst[c] = np.float32(factor * work[c])
        return
    m = 0
    while reach > _EXP_REACH and m < 12:  # beyond 2^12 _EXP_REACH float32 overflows
        reach *= 0.5
        m += 1
    t_scale = scale / 2.0 ** m
    k0, k1, k2 = _EXP_TAYLOR[0], _EXP_TAYLOR[1], _EXP_TAYLOR[2]
    for c in range(start, stop):
        t = t_scale * (src[c] - center)
        work[c] = (((((((k0 * t + k1) * t + k2) * t + k3) * t + k4) * t + k5) * t + k6) * t
                   + k7) * t + 1.0
    for _ in range(m):
        for c in range(start, stop):
            work[c] *= work[c]
    for c in range(start, stop):
        dst[c] = np.float32(factor * work[c])


@serial_kernel
def write_solution(x, d, alpha, steps, run_start, run_stop, row_first, labels, coef,
                   row_powers, s, out, r0, c0, sums, center, scale, offset, exponential,
                   final):
    """The solution v = x + alpha d + q on the runs after ``steps`` conjugate-gradient steps
    (alpha d + q after one, x unused; q alone after none, x and d unused; q as in
    :func:`subtract_poly_laplacian`) into the box of x's shape (h, w) at (r0, c0) of
    ``out`` (H, W) float32, NaN on the rest of the box.

    ``final`` (one component, whose mean ``center[0]`` is known): the output itself,
    scale (v - center) + offset, or with ``exponential`` exp(offset) exp(scale (v - center))
    (``center`` float64 array, ``scale``, ``offset`` float64). Else v, each run's sum
    (float64) added to sums[labels[run]], for :func:`finish_runs`.

    Each row is computed whole, then its gaps set to NaN (loops over a whole row are
    vectorised, loops over runs are not). The exponential is computed here (a float64
    Taylor polynomial after halving the exponent m times, squared m times; m per row, from
    the row's largest |v - center| on the mask), not by a separate pass of np.exp."""
    h, w = x.shape
    nan = np.float32(np.nan)
    v = np.empty(w, dtype=np.float64)
    work = np.empty(w, dtype=np.float64)
    factor = np.exp(offset)
    k = center[0]
    for r in range(h):
        out_r = out[r0 + r, c0:c0 + w]
        first, last = row_first[r], row_first[r + 1]
        if first == last:
            out_r[:] = nan
            continue
        _poly_row(coef, row_powers, s, r, v, w)
        d_r = d[r]
        if steps > 1:
            x_r = x[r]
            for c in range(w):
                v[c] += float(x_r[c] + alpha * d_r[c])
        elif steps == 1:  # x = 0 (take_direction's step 0 leaves it)
            for c in range(w):
                v[c] += float(alpha * d_r[c])
        if not final:
            for c in range(w):
                out_r[c] = np.float32(v[c])
            for i in range(first, last):
                sums[labels[i]] += _sum(out_r, run_start[i], run_stop[i])
        elif exponential:
            reach = 0.0
            for i in range(first, last):
                reach = max(reach, _max_deviation(v, run_start[i], run_stop[i], k))
            _exp_span(v, out_r, 0, w, k, scale, factor, abs(scale) * reach, work)
        else:
            for c in range(w):
                out_r[c] = np.float32(scale * (v[c] - k) + offset)
        cursor = 0
        for i in range(first, last):
            out_r[cursor:run_start[i]] = nan
            cursor = run_stop[i]
        out_r[cursor:] = nan


@serial_kernel
def finish_runs(out, r0, c0, h, w, run_start, run_stop, row_first, labels, center, scale,
                offset, exponential):
    """The values v written by :func:`write_solution` (not ``final``: several components)
    on the runs of the box of h x w pixels at (r0, c0) of ``out`` (H, W) float32 become
    scale (v - center[label]) + offset, or with ``exponential``
    exp(offset) exp(scale (v - center[label])) (as write_solution, m per run); NaN stays
    NaN. ``center`` (n_comp,) float64 (the components' means); ``scale``, ``offset``
    float64."""
    work = np.empty(w, dtype=np.float64)
    factor = np.exp(offset)
    for r in range(h):
        out_r = out[r0 + r, c0:c0 + w]
        for i in range(row_first[r], row_first[r + 1]):
            k = center[labels[i]]
            start, stop = run_start[i], run_stop[i]
            if exponential:
                reach = abs(scale) * _max_deviation(out_r, start, stop, k)
                _exp_span(out_r, out_r, start, stop, k, scale, factor, reach, work)
            else:
                for c in range(start, stop):
                    out_r[c] = np.float32(scale * (out_r[c] - k) + offset)


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


# After an edit of the compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
