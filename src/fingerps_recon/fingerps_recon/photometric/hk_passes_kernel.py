"""The compiled (numba) passes of the HK fit over a burst's pixels (paper Eq. 6-7), each one
loop over the chunks of ``CHUNK`` pixels (``prange``, one chunk per thread at a time) that
takes the pixels' Levenberg-Marquardt steps (:mod:`photometric.hk_step_kernel`) in the same
pass. Layout and vectorisation as :mod:`photometric.hk_model_kernel` describes them.

- With the global scale A held (:func:`solve_held`): the pixels need no global sum between
  iterations, and one pass does the whole solve of each chunk, its measurements and state
  in the core's cache (L1/L2), from the gathering to the result images.
- With A fitted jointly with the pixels (:mod:`photometric.hk_joint_fit` runs them): A's
  and rho's linear fit (:func:`linear_sums`), the start (:func:`start`), the candidates at a
  trial A (:func:`candidate`), the commit fused with the next step (:func:`commit`), and the
  result images (:func:`finish`). The global sums (A's fit, the Schur complement, the total
  cost) are returned per chunk in float64 and added up by the caller in a fixed order, so
  the result does not depend on the number of threads.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from fingerps_recon.photometric import hk_step_kernel
from fingerps_recon.photometric.hk_gather_kernel import gather_chunk
from fingerps_recon.photometric.hk_model_kernel import (
    CHUNK,
    N_MEAS,
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


@serial_kernel
def _predicted_decrease(sums, delta0):
    """The decrease of the cost that the Gauss–Newton model predicts at least for the
    steps ``delta0`` of a chunk whose state is in columns 0 .. CHUNK (float64): the sum of
    (J^T r) . delta. For a damped step delta = (H + D)^-1 J^T r (D >= 0 diagonal) the
    model's decrease 2 (J^T r) . delta - delta^T H delta lies between that and twice it."""
    total = 0.0
    for i in range(CHUNK):
        total += (float(sums[6, i]) * float(delta0[0, i]) + float(sums[7, i]) * float(delta0[1, i])
                  + float(sums[8, i]) * float(delta0[2, i]))
    return total


@parallel_kernel
def solve_held(cand, index, images, usable, normals_in, albedo_in, terms, views, bad, min_cr,
               scale, a_tau, neg_tau, consts, lam_start, iterations, tol, solved, counts,
               normals, albedo, rms, valid, flags, parts):
    """The whole solve at a known A = ``scale`` (float64), chunk by chunk: with A held, the
    pixels do not depend on each other, so each chunk is gathered (:func:`gather_chunk`,
    arguments as :func:`photometric.hk_gather_kernel.gather`), solved and written out
    (:func:`hk_step_kernel.finish_chunk`) while its measurements and state stay in the
    core's cache -- one pass over the burst instead of two per iteration. The same steps as
    the passes with A fixed: rho in closed form at the initial normals, then up to ``iterations``
    Levenberg–Marquardt iterations (damping from ``lam_start``), each pixel keeping the
    better of its state and its candidate; a chunk stops once the decrease its next steps
    promise (:func:`_predicted_decrease`) is at most ``tol`` times its cost, without
    evaluating them. Per chunk into ``parts`` (chunks, 5) float64: the initial and the
    final cost, the iterations done, and the numerator and denominator of A's linear fit
    (with every rho) at the final normals, sum (P.I - P.C C.I / C.C) and
    sum (P.P - (P.C)^2 / C.C), for the A the next burst is held at; ``flags`` (chunks,)
    as :func:`photometric.hk_gather_kernel.gather`."""
    k_count = images.shape[0]
    a = np.float32(scale)
    f32 = np.float32
    for chunk in prange(parts.shape[0]):
        meas = np.empty((1, k_count, N_MEAS, CHUNK), f32)
        v = np.empty((3, CHUNK), f32)
        n = np.empty((3, CHUNK), f32)
        rho = np.empty(CHUNK, f32)
        n_new = np.empty((3, CHUNK), f32)
        rho_new = np.empty(CHUNK, f32)
        lam = np.full(CHUNK, lam_start, f32)
        sums = np.empty((N_SUMS, CHUNK), f32)
        sums_new = np.empty((N_SUMS, CHUNK), f32)
        delta0 = np.empty((3, CHUNK), f32)
        w = np.empty((3, CHUNK), f32)
        rows = np.empty((5, CHUNK), f32)
        scr = np.empty(SCRATCH, f32)
        acc = np.empty(N_SUMS * CHUNK, f32)
        chosen = np.empty(CHUNK)
        flags[chunk] = gather_chunk(chunk, cand, index, images, usable, normals_in,
                                    albedo_in, terms, views, bad, min_cr, meas[0], v, n, rho,
                                    0, solved, counts)
        view_terms(n, v, 0, consts, scr)
        linear_rows(n, meas, 0, neg_tau, consts, scr, rows)
        hk_step_kernel.fit_rho(0, rows, scale, rho)
        model_sums(n, rho, 0, a, a_tau, neg_tau, meas, consts, scr, acc, sums)
        hk_step_kernel.steps(0, sums, lam, consts, delta0, w)
        cost = 0.0
        for i in range(CHUNK):
            cost += float(sums[14, i])
        parts[chunk, 0] = cost
        done = 0
        while done < iterations and _predicted_decrease(sums, delta0) > tol * cost:
            done += 1
            hk_step_kernel.trial_state(0, n, rho, delta0, w, f32(0.0), n_new, rho_new)
            view_terms(n_new, v, 0, consts, scr)
            model_sums(n_new, rho_new, 0, a, a_tau, neg_tau, meas, consts, scr, acc,
                       sums_new)
            hk_step_kernel.keep_better(0, 0.0, 0.0, consts, sums, sums_new, n, n_new, rho,
                                       rho_new, lam, scr, chosen)
            hk_step_kernel.steps(0, sums, lam, consts, delta0, w)
            cost = 0.0
            for i in range(CHUNK):
                cost += chosen[i]
        parts[chunk, 1] = cost
        parts[chunk, 2] = done
        # A's linear fit at the final normals, from the final sums (r = I - A P - rho C):
        # P.I = P.r + A P.P + rho P.C, C.I = C.r + A P.C + rho C.C.
        num = den = 0.0
        for i in range(CHUNK):
            pp, pc, cc = float(sums[12, i]), float(sums[11, i]), float(sums[5, i])
            rho_i = float(rho[i])
            p_i = float(sums[13, i]) + scale * pp + rho_i * pc
            c_i = float(sums[8, i]) + scale * pc + rho_i * cc
            if cc > 0.0:
                num += p_i - pc * c_i / cc
                den += pp - pc * pc / cc
        parts[chunk, 3] = num
        parts[chunk, 4] = den
        hk_step_kernel.finish_chunk(cand, solved, chunk * CHUNK, n, rho, sums, 0, counts,
                                    normals, albedo, rms, valid)


# The kernels here compile the helpers they call with what those inline (the steps'
# adjugate: photometric.symmetric_solve); after an edit of any of those modules, or of the
# compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
