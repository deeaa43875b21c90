"""Compiled pass of the FAST solver (:mod:`surface.integration_fast`) over the mask's runs
alone (:func:`run_topology`): the 4-connected components (union-find over the runs,
:func:`_find`), the outline (the mask pixels with a 4-neighbour in the DCT box but outside
the mask, where the conjugate-gradient residual lives: each run less the segments
:func:`_clip_segments` finds covered above and below) and, summed over the same edges from
prefix sums along the runs, the Gram matrix V^T A V of the polynomial space
(:mod:`surface.integration_polynomials`) and the mask's moments.

Runs on the calling thread (``serial_kernel``), cached on disk as the other kernels;
importing this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)


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


@inline_kernel
def _first_run_ending_after(run_stop, k, last, column):
    """The first of the runs k:last (sorted, disjoint) that ends after ``column``, or last."""
    while k < last and run_stop[k] <= column:
        k += 1
    return k


@inline_kernel
def _first_run_starting_at(run_start, k, last, column):
    """The first of the runs k:last (sorted, disjoint) that starts at ``column`` or after,
    or last: the runs k ... before it are those that may overlap columns before ``column``."""
    while k < last and run_start[k] < column:
        k += 1
    return k


@serial_kernel
def _clip_segments(src_lo, src_hi, n_seg, run_start, run_stop, first, last, dst_lo, dst_hi):
    """dst = the segments src[:n_seg] (sorted, disjoint) clipped to the runs first:last of
    another row (sorted, disjoint); returns their number."""
    out = 0
    k = first
    for i in range(n_seg):
        a, z = src_lo[i], src_hi[i]
        k = _first_run_ending_after(run_stop, k, last, a)
        for j in range(k, _first_run_starting_at(run_start, k, last, z)):
            s, e = max(a, run_start[j]), min(z, run_stop[j])
            if s < e:
                dst_lo[out] = s
                dst_hi[out] = e
                out += 1
    return out


@serial_kernel
def run_topology(run_start, run_stop, row_first, w2, pair_prefix, power_prefix, row_powers,
                 row_steps, basis_a, basis_b, labels, outline_rows, outline_cols, gram,
                 mask_moments, seg_lo, seg_hi):
    """Components, outline pixels and the polynomial space's Gram matrix, from the runs.

    ``run_start``, ``run_stop``, ``row_first`` as written by
    :func:`surface.integration_rhs_kernel.assemble_rhs` for a box of
    h = row_first.size - 1 rows and w columns, in a DCT box of h x ``w2`` (w2 >= w: the
    columns from w on are outside the mask).
    Monomials s^a t^b (a = ``basis_a[i]``, b = ``basis_b[i]``, 1 <= a + b <= d) in the
    coordinates s(c), t(r) of :func:`surface.integration_polynomials.poly_tables`, whose
    tables are: ``pair_prefix`` (w, d * d) float64, pair_prefix[c, (a - 1) d + a' - 1] = sum over
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
                k = _first_run_ending_after(run_stop, k, up_last, c0)
                for j in range(k, _first_run_starting_at(run_start, k, up_last, c1)):
                    s, e = max(c0, run_start[j]), min(c1, run_stop[j])
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


# After an edit of the compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
