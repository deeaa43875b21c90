"""Compiled passes that write the FAST solver's solution (:mod:`surface.integration_fast`)
into the caller's output: :func:`write_solution` (the solution on the mask's runs, NaN on
the rest of the box; with one component, whose mean is known, the output itself) and
:func:`finish_runs` (with several components, each one's mean taken out in a second pass).

For a depth the output is exp(offset) exp(scale (v - mean)) (:mod:`surface.integration`'s
log-depth), computed by :func:`_exp_span` in float64 and rounded once to float32: a Taylor
polynomial of exp after the exponent is halved m times, squared m times.

Each row is computed whole, then patched (loops over a whole row are vectorised, loops over
runs are not). Run on the calling thread (``serial_kernel``), cached on disk as the other
kernels; importing this module needs numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)
from fingerps_recon.surface.integration_polynomial_kernel import poly_row
from fingerps_recon.surface.integration_sum_kernel import ordered_sum

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
    :func:`surface.integration_polynomial_kernel.subtract_poly_laplacian`) into the box of
    x's shape (h, w) at (r0, c0) of ``out`` (H, W) float32, NaN on the rest of the box.

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
        poly_row(coef, row_powers, s, r, v, w)
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
                sums[labels[i]] += ordered_sum(out_r, run_start[i], run_stop[i])
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


# After an edit of the compile options or of a module whose kernels these inline, the cached
# kernels are compiled anew.
drop_stale_caches(globals())
