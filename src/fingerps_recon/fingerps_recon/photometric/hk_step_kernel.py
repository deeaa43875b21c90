"""The Levenberg–Marquardt steps of the HK fit (paper Eq. 6-7) on one chunk of pixels, compiled
(numba) for the passes of :mod:`photometric.hk_passes_kernel`: the damped Gauss–Newton steps
from each pixel's sums (:func:`steps`, its 3x3 system solved by the adjugate), rho in closed
form for a given A (:func:`fit_rho`), the candidate states (:func:`trial_state`), each pixel
keeping the better of its state and its candidate (:func:`keep_better`), and the result
images (:func:`finish_chunk`). Layout and vectorisation as :mod:`photometric.hk_model_kernel`
describes them."""

from __future__ import annotations

import math

import numba
import numpy as np

from fingerps_recon.photometric.hk_model_kernel import (
    CHUNK,
    LAMBDA_DOWN,
    LAMBDA_MAX,
    LAMBDA_MIN,
    LAMBDA_UP,
    N_SUMS,
    TAKE,
    fmax,
    fmin,
)
from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)
from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)
_TINY_TRACE = np.float32(1e-7)
_TINY = np.float32(1e-30)
_SINGULAR = np.float32(1e-6)

# The symmetric 3x3 solve by the adjugate (photometric.symmetric_solve), inlined.
_adjugate = inline_kernel(symmetric_adjugate)
_adjugate_solve = inline_kernel(adjugate_solve)


@serial_kernel
def steps(j0, sums, lam, consts, delta0, w):
    """Damped Gauss–Newton steps of the chunk's pixels: delta0 = Hd^-1 J^T r,
    w = Hd^-1 J^T P with Hd = H + lambda diag(H) inverted by its adjugate
    (:mod:`photometric.symmetric_solve`); a (nearly) singular Hd gives a zero step and
    raises the pixel's damping."""
    up, top = consts[LAMBDA_UP], consts[LAMBDA_MAX]
    for i in range(CHUNK):
        j = _U(j0 + i)
        h11, h12, h13 = sums[0, j], sums[1, j], sums[2, j]
        h22, h23, h33 = sums[3, j], sums[4, j], sums[5, j]
        lj = lam[j]
        tiny = (h11 + h22 + h33) * _TINY_TRACE + _TINY
        d1 = h11 + lj * fmax(h11, tiny)
        d2 = h22 + lj * fmax(h22, tiny)
        d3 = h33 + lj * fmax(h33, tiny)
        a11, a12, a13, a22, a23, a33, det = _adjugate(d1, h12, h13, d2, h23, d3)
        ok = det > _SINGULAR * d1 * d2 * d3
        inv = _F1 / det
        inv_det = inv if ok else _F0
        raised = fmin(lj * up, top)
        lam[j] = lj if ok else raised  # (nearly) singular: no step, more damping next time
        g1, g2, g3 = sums[6, j], sums[7, j], sums[8, j]
        c1, c2, c3 = sums[9, j], sums[10, j], sums[11, j]
        delta0[0, j], delta0[1, j], delta0[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, g1, g2, g3)
        w[0, j], w[1, j], w[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, c1, c2, c3)


@serial_kernel
def fit_rho(j0, rows, scale, rho):
    """rho of the chunk's pixels at ``j0`` in closed form for A = ``scale`` (float64) from
    the linear fit's per-pixel sums ``rows``
    (:func:`photometric.hk_model_kernel.linear_rows`): (C.I - A P.C) / C.C, >= 0; kept
    where C.C = 0."""
    for i in range(CHUNK):
        j = _U(j0 + i)
        pc, cc, c_i = float(rows[1, j]), float(rows[2, j]), float(rows[4, j])
        fitted = fmax((c_i - scale * pc) / fmax(cc, 1e-30), 0.0)
        kept = float(rho[j])
        rho[j] = fitted if cc > 0.0 else kept


@serial_kernel
def trial_state(j0, n, rho, delta0, w, d32, n_new, rho_new):
    """The chunk's candidate states: the step delta0 - d32 w (float32; d32 = trial A - A)
    along the tangent directions, the normal renormalised, and in rho (>= 0)."""
    for i in range(CHUNK):
        j = _U(j0 + i)
        sa = delta0[0, j] - d32 * w[0, j]
        sb = delta0[1, j] - d32 * w[1, j]
        sr = delta0[2, j] - d32 * w[2, j]
        nx, ny, nz = n[0, j], n[1, j], n[2, j]
        # n + a t_x + b t_y, t_x = e_x - n_x n, t_y = e_y - n_y n
        mx = nx + sa * (-nx * nx + _F1) + sb * (-ny * nx)
        my = ny + sa * (-nx * ny) + sb * (-ny * ny + _F1)
        mz = nz + sa * (-nx * nz) + sb * (-ny * nz)
        norm = np.sqrt(mx * mx + my * my + mz * mz)
        n_new[0, j] = mx / norm
        n_new[1, j] = my / norm
        n_new[2, j] = mz / norm
        rho_new[j] = fmax(rho[j] + sr, _F0)


@serial_kernel
def keep_better(j0, d_old, d_new, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
                 scr, chosen):
    """The commit's choice for the chunk's pixels: each keeps the better of its state and
    its candidate at A = at (``d_old`` = at - A, ``d_new`` = at - trial; float64), with
    their sums brought to that A and the damping adapted; the chosen costs (float64) into
    ``chosen``."""
    d_old32, d_new32 = np.float32(d_old), np.float32(d_new)
    down, up = consts[LAMBDA_DOWN], consts[LAMBDA_UP]
    low, top = consts[LAMBDA_MIN], consts[LAMBDA_MAX]
    # Loops that write few arrays each (LLVM checks at run time that the arrays a
    # loop writes do not overlap the others, and vectorises only below a limit).
    for i in range(CHUNK):
        j = _U(j0 + i)
        old_d, old_ga, old_c = float(sums[12, j]), float(sums[13, j]), float(sums[14, j])
        new_d, new_ga = float(sums_new[12, j]), float(sums_new[13, j])
        old = old_c + d_old * (d_old * old_d - 2.0 * old_ga)
        new = float(sums_new[14, j]) + d_new * (d_new * new_d - 2.0 * new_ga)
        accept = new <= old  # never a non-finite candidate
        scr[_U(TAKE + i)] = _F1 if accept else _F0
        chosen[i] = new if accept else old
    for row in range(N_SUMS):  # J^T J, J^T P, P.P of the kept state (the rest below)
        if 6 <= row <= 8 or row >= 13:
            continue
        for i in range(CHUNK):
            j = _U(j0 + i)
            cand, kept = sums_new[row, j], sums[row, j]
            sums[row, j] = cand if scr[_U(TAKE + i)] > _F0 else kept
    for i in range(CHUNK):
        # J^T r, P.r, r.r of the kept state at A = at (n, rho unchanged, J kept)
        j = _U(j0 + i)
        accept = scr[_U(TAKE + i)] > _F0
        delta = d_new32 if accept else d_old32
        g1n, g2n, g3n = sums_new[6, j], sums_new[7, j], sums_new[8, j]
        gan, costn = sums_new[13, j], sums_new[14, j]
        g1o, g2o, g3o = sums[6, j], sums[7, j], sums[8, j]
        gao, costo = sums[13, j], sums[14, j]
        g1 = g1n if accept else g1o
        g2 = g2n if accept else g2o
        g3 = g3n if accept else g3o
        ga = gan if accept else gao
        cost = costn if accept else costo
        dd = sums[12, j]
        sums[14, j] = cost + delta * (delta * dd - _F2 * ga)
        sums[6, j] = g1 - delta * sums[9, j]
        sums[7, j] = g2 - delta * sums[10, j]
        sums[8, j] = g3 - delta * sums[11, j]
        sums[13, j] = ga - delta * dd
    for i in range(CHUNK):
        j = _U(j0 + i)
        accept = scr[_U(TAKE + i)] > _F0
        nx, ny, nz, rho_j = n_new[0, j], n_new[1, j], n_new[2, j], rho_new[j]
        ox, oy, oz, rho_o = n[0, j], n[1, j], n[2, j], rho[j]
        n[0, j] = nx if accept else ox
        n[1, j] = ny if accept else oy
        n[2, j] = nz if accept else oz
        rho[j] = rho_j if accept else rho_o
        lj = lam[j] * (down if accept else up)
        lam[j] = fmin(fmax(lj, low), top)


@serial_kernel
def finish_chunk(pix, solved, j0, n, rho, sums, d0, counts, normals, albedo, rms, valid):
    """The result images (flat (H*W,)) at the chunk's pixels ``pix[j0:j0 + CHUNK]``, whose
    state is in the columns ``d0 .. d0 + CHUNK`` of ``n``, ``rho``, ``sums``: a solved pixel
    is valid if its normal and albedo are finite and its 3x3 J^T J is non-singular (its
    solution is determined); ``rms`` = sqrt(r.r / counts)."""
    for i in range(min(CHUNK, pix.shape[0] - j0)):
        j = j0 + i
        d = d0 + i
        h11, h12, h13 = float(sums[0, d]), float(sums[1, d]), float(sums[2, d])
        h22, h23, h33 = float(sums[3, d]), float(sums[4, d]), float(sums[5, d])
        det = _adjugate(h11, h12, h13, h22, h23, h33)[6]
        ok = (solved[j] and det > 1e-9 * h11 * h22 * h33 and math.isfinite(n[0, d])
              and math.isfinite(n[1, d]) and math.isfinite(n[2, d])
              and math.isfinite(rho[d]))
        if ok:
            p = pix[j]
            normals[p, 0], normals[p, 1], normals[p, 2] = n[0, d], n[1, d], n[2, d]
            albedo[p] = rho[d]
            rms[p] = math.sqrt(fmax(float(sums[14, d]), 0.0) / counts[j])
            valid[p] = True


# After an edit of a module whose functions the kernels here compile, or of the
# compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
