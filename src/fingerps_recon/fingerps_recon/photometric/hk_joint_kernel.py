"""The compiled (numba) passes of the HK fit with the global scale A fitted jointly with the
pixels (paper Eq. 6-7; :mod:`photometric.hk_joint_fit` runs them): A's and rho's linear fit
(:func:`linear_sums`), the start (:func:`start`), the candidates at a trial A
(:func:`candidate`), the commit fused with the next step (:func:`commit`), and the result
images (:func:`finish`). Each is one loop over the chunks of ``CHUNK`` pixels (``prange``,
one chunk per thread at a time) that takes the pixels' steps in the same pass; the global
sums (A's fit, the Schur complement, the total cost) are returned per chunk in float64 and
added up by the caller in a fixed order, so the result does not depend on the number of
threads. Layout and vectorisation as :mod:`photometric.hk_model_kernel` describes them."""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from fingerps_recon.photometric import hk_step_kernel
from fingerps_recon.photometric.hk_model_kernel import (
    CHUNK,
    N_SUMS,
    SCRATCH,
    fmax,
    linear_rows,
    model_sums,
    view_terms,
)
from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    parallel_kernel,
    serial_kernel,
)

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64


@serial_kernel
def _step_parts(j0, sums, delta0, w, parts, chunk):
    """The chunk's parts of the Schur complement on A into ``parts[chunk, 1:5]`` (float64):
    P.r, (J^T P).delta0, P.P, (J^T P).w."""
    ga = cd = dd = cw = 0.0
    for i in range(CHUNK):
        j = _U(j0 + i)
        c1, c2, c3 = sums[9, j], sums[10, j], sums[11, j]
        ga += float(sums[13, j])
        dd += float(sums[12, j])
        cd += float(c1 * delta0[0, j]) + float(c2 * delta0[1, j]) + float(c3 * delta0[2, j])
        cw += float(c1 * w[0, j]) + float(c2 * w[1, j]) + float(c3 * w[2, j])
    parts[chunk, 1], parts[chunk, 2], parts[chunk, 3], parts[chunk, 4] = ga, cd, dd, cw


@parallel_kernel
def linear_sums(n, meas, views, neg_tau, consts, rows, parts):
    """The per-pixel sums of A's and rho's joint linear fit (:func:`linear_rows`) into
    ``rows``, and per chunk the parts of the fit's numerator sum (P.I - P.C C.I / C.C) and
    denominator sum (P.P - (P.C)^2 / C.C) into ``parts`` (chunks, 2) float64."""
    for chunk in prange(parts.shape[0]):
        j0 = chunk * CHUNK
        scr = np.empty(SCRATCH, np.float32)
        view_terms(n, views, j0, consts, scr)
        linear_rows(n, meas, chunk, neg_tau, consts, scr, rows)
        num = den = 0.0
        for i in range(CHUNK):
            j = _U(j0 + i)
            pp, pc = float(rows[0, j]), float(rows[1, j])
            cc = fmax(float(rows[2, j]), 1e-30)
            num += float(rows[3, j]) - pc * float(rows[4, j]) / cc
            den += pp - pc * pc / cc
        parts[chunk, 0] = num
        parts[chunk, 1] = den


@parallel_kernel
def start(n, rho, lam, rows, scale, a_tau, neg_tau, meas, views, consts, sums, delta0, w,
          parts, rows_given):
    """rho in closed form for A = ``scale`` (float64) at the initial normals -- from
    ``rows`` of :func:`linear_sums` if ``rows_given``, else formed here, chunk by chunk (A
    known beforehand: one pass over the measurements less) --, the pixels' sums there and
    their first step. Per chunk into ``parts`` (chunks, 5) float64: the cost and the Schur
    parts (:func:`_step_parts`)."""
    a = np.float32(scale)
    for chunk in prange(parts.shape[0]):
        j0 = chunk * CHUNK
        scr = np.empty(SCRATCH, np.float32)
        view_terms(n, views, j0, consts, scr)
        if not rows_given:
            linear_rows(n, meas, chunk, neg_tau, consts, scr, rows)
        hk_step_kernel.fit_rho(j0, rows, scale, rho)
        model_sums(n, rho, chunk, a, a_tau, neg_tau, meas, consts, scr,
                   np.empty(N_SUMS * CHUNK, np.float32), sums)
        hk_step_kernel.steps(j0, sums, lam, consts, delta0, w)
        _step_parts(j0, sums, delta0, w, parts, chunk)
        cost = 0.0
        for i in range(CHUNK):
            cost += float(sums[14, _U(j0 + i)])
        parts[chunk, 0] = cost


@parallel_kernel
def candidate(n, rho, delta0, w, scale, trial, a_tau, neg_tau, meas, views, consts, sums,
              n_new, rho_new, sums_new, parts):
    """Each pixel's candidate for A -> ``trial`` (float64; step delta0 - (trial - A) w along
    the tangent directions and in rho), its sums at ``trial``, and the choice at ``trial``:
    per chunk into ``parts`` (chunks, 3) float64 the chosen cost, P.r and P.P."""
    d_scale = trial - scale
    d32 = np.float32(d_scale)
    a = np.float32(trial)
    for chunk in prange(parts.shape[0]):
        j0 = chunk * CHUNK
        scr = np.empty(SCRATCH, np.float32)
        hk_step_kernel.trial_state(j0, n, rho, delta0, w, d32, n_new, rho_new)
        view_terms(n_new, views, j0, consts, scr)
        model_sums(n_new, rho_new, chunk, a, a_tau, neg_tau, meas, consts, scr,
                   np.empty(N_SUMS * CHUNK, np.float32), sums_new)
        cost = ga = dd = 0.0
        for i in range(CHUNK):
            j = _U(j0 + i)
            old_d, old_ga = float(sums[12, j]), float(sums[13, j])
            old = float(sums[14, j]) + d_scale * (d_scale * old_d - 2.0 * old_ga)
            new = float(sums_new[14, j])
            if new <= old:
                cost += new
                ga += float(sums_new[13, j])
                dd += float(sums_new[12, j])
            else:
                cost += old
                ga += old_ga - d_scale * old_d
                dd += old_d
        parts[chunk, 0] = cost
        parts[chunk, 1] = ga
        parts[chunk, 2] = dd


@parallel_kernel
def commit(n, rho, lam, scale, trial, at, consts, sums, n_new, rho_new, sums_new, delta0, w,
           parts):
    """Each pixel keeps the better of its state and its candidate at A = ``at`` (float64;
    their sums brought to that A: r -> r - (at - A) P), adapts its damping and takes its
    next step. Per chunk into ``parts`` (chunks, 5) float64: the cost and the Schur parts
    (:func:`_step_parts`)."""
    d_old, d_new = at - scale, at - trial
    for chunk in prange(parts.shape[0]):
        j0 = chunk * CHUNK
        scr = np.empty(SCRATCH, np.float32)
        chosen = np.empty(CHUNK)  # the chosen states' costs at A = at, float64
        hk_step_kernel.keep_better(j0, d_old, d_new, consts, sums, sums_new, n, n_new, rho,
                                   rho_new, lam, scr, chosen)
        hk_step_kernel.steps(j0, sums, lam, consts, delta0, w)
        _step_parts(j0, sums, delta0, w, parts, chunk)
        cost = 0.0
        for i in range(CHUNK):
            cost += chosen[i]
        parts[chunk, 0] = cost


@parallel_kernel
def finish(pix, solved, n, rho, sums, counts, normals, albedo, rms, valid):
    """The result images (flat (H*W,), zeros where not valid) from the state of every chunk
    (:func:`hk_step_kernel.finish_chunk`)."""
    for chunk in prange((pix.shape[0] + CHUNK - 1) // CHUNK):
        j0 = chunk * CHUNK
        hk_step_kernel.finish_chunk(pix, solved, j0, n, rho, sums, j0, counts, normals, albedo,
                                    rms, valid)


# The kernels here compile the helpers they call with what those inline (the steps'
# adjugate: photometric.symmetric_solve); after an edit of any of those modules, or of the
# compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
