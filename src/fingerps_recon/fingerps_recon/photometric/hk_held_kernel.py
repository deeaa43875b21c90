"""The HK solve with the global scale A held (paper Eq. 6-7), compiled (numba): with A held
the pixels need no global sum between iterations, and one pass (:func:`solve_held`,
``prange`` over the chunks of ``CHUNK`` pixels) does the whole solve of each chunk, its
measurements and state in the core's cache (L1/L2), from the gathering to the result
images. Layout and vectorisation as :mod:`photometric.hk_model_kernel` describes them."""

from __future__ import annotations

import numpy as np
from numba import prange

from fingerps_recon.photometric import hk_step_kernel
from fingerps_recon.photometric.hk_gather_kernel import gather_chunk
from fingerps_recon.photometric.hk_model_kernel import (
    CHUNK,
    N_MEAS,
    N_SUMS,
    SCRATCH,
    linear_rows,
    model_sums,
    view_terms,
)
from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    parallel_kernel,
    serial_kernel,
)


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
    (:func:`hk_step_kernel.finish_chunk`) while its measurements and state stay in the core's cache --
    one pass over the burst instead of two per iteration. The same steps as the passes
    with A fixed: rho in closed form at the initial normals, then up to ``iterations``
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
