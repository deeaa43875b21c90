"""Compiled (numba) passes of the HK solver (:mod:`photometric.hk_solver`, backend "numba").

The same Levenberg–Marquardt algorithm as the solver's numpy backend -- the same residual,
Jacobian, damping, accept/reject and Schur-complement step for the global scale A, in the
same float32 arithmetic -- with each pass over the pixels fused: per chunk of ``CHUNK``
pixels (``prange`` over the chunks, one chunk per thread at a time) the model, its Jacobian
and the 15 Gauss–Newton sums of every pixel are formed measurement by measurement while the
chunk's sums stay in the core's L1 cache, the step is taken in the same pass, and nothing
of size (K, N) is written. The loops over a chunk's pixels are written so that LLVM
vectorises them (AVX2: 8 pixels at a time): no calls (``_exp`` is inlined arithmetic), no
branches (selects), unit strides. The global sums (A's fit, the Schur complement, the
total cost) are returned per chunk in float64 and added up by the caller in a fixed order,
so the result does not depend on the number of threads.

Layout, as the numpy backend's columns: ``values`` (I where usable, else 0) and ``usable``
(K, N); ``lights`` (3, K, N) or (3, K, 1); ``views`` (3, N) or (3, 1); ``intensity`` e_k
and ``phase`` e_k p(c, g) (K, N) or (K, 1); the state component-major: normals (3, N),
sums (15, N) with rows ``_H11`` ... ``_COST`` of the solver. Scalars: ``a`` (A), ``a_tau``
(A tau_d) and ``neg_tau`` (-tau_d) as float32; ``consts`` float32 (indices below).

The pixels are also gathered from the images (:func:`select_pixels`, :func:`gather`, as
the numpy backend's ``_prepare``) and the result images written (:func:`finish`) here.
Everything matches the numpy backend operation for operation except exp(): the numpy
backend uses ``cv2.exp``, this module an inlined polynomial (Cephes expf, relative error
< 2e-7); results agree to float32 rounding, not bit for bit.

Importing this module needs numba (ImportError otherwise; the solver then uses numpy). The
compiled code is cached on disk (``cache=True``: in the package's ``__pycache__``, else the
user's cache directory, or ``NUMBA_CACHE_DIR`` when set); where no cache directory is
writable the kernels are compiled in every process (a warning says so).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    parallel_kernel,
    serial_kernel,
)
from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64

# Pixels per chunk of the parallel loops (the chunk's scratch arrays stay in the core's
# L1/L2 cache).
CHUNK = 256
# Indices into ``consts`` (float32).
VALUE_FLOOR, DERIVATIVE_FLOOR, LAMBDA_DOWN, LAMBDA_UP, LAMBDA_MIN, LAMBDA_MAX = range(6)
N_CONSTS = 6
N_SUMS = 15
# Offsets of the rows of a chunk's 1-D scratch arrays (indexed _U(offset + i): rows at
# constant distances, which LLVM tells apart without run-time overlap checks). ``scr``: the
# view direction and derived per-pixel terms, the current measurement's light direction,
# e p and e, and the commit's choice (1 or 0); ``terms``: the current measurement's Jacobian
# columns j1, j2 (tangent steps), C = e c_i, P = e p S and r = I - f; ``acc``: the 15 sums
# (or the linear fit's 5) being accumulated. Separate arrays, and few rows written per loop:
# LLVM's loop vectorizer gives up on loops with more dependences than it analyses.
(_VX, _VY, _VZ, _CR, _INV_CR, _DINV_CR, _VTX, _VTY, _SEEN, _LX, _LY, _LZ, _G, _E, _TAKE) = (
    row * CHUNK for row in range(15)
)
_SCRATCH = 15 * CHUNK
_J1, _J2, _C, _P, _R = (row * CHUNK for row in range(5))
_TERMS = 5 * CHUNK
_ACC = tuple(row * CHUNK for row in range(N_SUMS))

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)
_HALF = np.float32(0.5)
_TINY_TRACE = np.float32(1e-7)
_TINY = np.float32(1e-30)
_SINGULAR = np.float32(1e-6)
# exp(x) for float32 x (Cephes expf): 2^n e^r, |r| <= ln2 / 2; below _EXP_LO (e^x < 1.2e-38,
# the smallest normal float32) it returns 1.2e-38.
_EXP_LO = np.float32(-87.33)
_LOG2E = np.float32(1.44269504088896341)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EXP_P = tuple(np.float32(c) for c in (
    1.9875691500e-4, 1.3981999507e-3, 8.3334519073e-3, 4.1665795894e-2, 1.6666665459e-1,
    5.0000001201e-1,
))
_P0, _P1, _P2, _P3, _P4, _P5 = _EXP_P
_BIAS = np.int32(127)
_MANTISSA = np.int32(23)


# The symmetric 3x3 solve by the adjugate (photometric.symmetric_solve), inlined.
_adjugate = inline_kernel(symmetric_adjugate)
_adjugate_solve = inline_kernel(adjugate_solve)


@inline_kernel
def _exp(x):
    """exp(x), float32, relative error < 2e-7 for x >= -87.33 (branch-free, inlined)."""
    x = max(x, _EXP_LO)
    fn = np.floor(x * _LOG2E + _HALF)
    r = x - fn * _LN2_HI
    r = r - fn * _LN2_LO
    poly = ((((_P0 * r + _P1) * r + _P2) * r + _P3) * r + _P4) * r + _P5
    poly = poly * (r * r) + r + _F1
    bits = (np.int32(fn) + _BIAS) << _MANTISSA  # 2^fn
    return poly * np.int32(bits).view(np.float32)


@serial_kernel
def _chunk_span(chunk, count):
    start = chunk * CHUNK
    return start, min(start + CHUNK, count) - start


@serial_kernel
def _view_terms(n, j0, m, views, consts, scr):
    """Per pixel of the chunk: c_r = v.n (floored), 1/c_r, the capped 1/c_r of the
    derivatives, v.t_x, v.t_y for the tangent directions t = e - n_axis n, and whether
    v.n > 0 (1 or 0), into the scratch."""
    if views.shape[1] > 1:
        for i in range(m):
            j = _U(j0 + i)
            scr[_U(_VX + i)] = views[0, j]
            scr[_U(_VY + i)] = views[1, j]
            scr[_U(_VZ + i)] = views[2, j]
    else:
        vx, vy, vz = views[0, 0], views[1, 0], views[2, 0]
        for i in range(m):
            scr[_U(_VX + i)], scr[_U(_VY + i)], scr[_U(_VZ + i)] = vx, vy, vz
    value_floor = consts[VALUE_FLOOR]
    derivative_floor = consts[DERIVATIVE_FLOOR]
    for i in range(m):
        j = _U(j0 + i)
        nx, ny, nz = n[0, j], n[1, j], n[2, j]
        vx, vy, vz = scr[_U(_VX + i)], scr[_U(_VY + i)], scr[_U(_VZ + i)]
        cr = vx * nx
        cr += vy * ny
        cr += vz * nz
        scr[_U(_SEEN + i)] = _F1 if cr > _F0 else _F0
        cr = max(cr, value_floor)
        scr[_U(_CR + i)] = cr
        scr[_U(_INV_CR + i)] = _F1 / cr
        scr[_U(_DINV_CR + i)] = _F1 / max(cr, derivative_floor)
        scr[_U(_VTX + i)] = vx - cr * nx
        scr[_U(_VTY + i)] = vy - cr * ny


@inline_kernel
def _row_into_scratch(k, j0, m, per_light, row, scr):
    """Row k of ``per_light`` over the chunk's pixels (``per_light`` (K, N)), or its one value
    for every pixel (``per_light`` (K, 1)), into the scratch row at offset ``row``."""
    if per_light.shape[1] > 1:
        for i in range(m):
            scr[_U(row + i)] = per_light[k, _U(j0 + i)]
    else:
        value = per_light[k, 0]
        for i in range(m):
            scr[_U(row + i)] = value


@serial_kernel
def _light_terms(k, j0, m, lights, intensity, phase, scr):
    """Light k's direction, e_k p and e_k for the chunk's pixels into the scratch."""
    if lights.shape[2] > 1:
        for i in range(m):
            j = _U(j0 + i)
            scr[_U(_LX + i)] = lights[0, k, j]
            scr[_U(_LY + i)] = lights[1, k, j]
            scr[_U(_LZ + i)] = lights[2, k, j]
    else:
        lx, ly, lz = lights[0, k, 0], lights[1, k, 0], lights[2, k, 0]
        for i in range(m):
            scr[_U(_LX + i)], scr[_U(_LY + i)], scr[_U(_LZ + i)] = lx, ly, lz
    _row_into_scratch(k, j0, m, phase, _G, scr)
    _row_into_scratch(k, j0, m, intensity, _E, scr)


@serial_kernel
def _model_sums(n, rho, j0, m, a, a_tau, neg_tau, values, usable, lights, intensity, phase,
                consts, scr, terms, acc, sums):
    """The 15 Gauss–Newton sums of the chunk's pixels at normals ``n``, albedo ``rho`` and
    A = ``a`` into ``sums[:, j0:j0 + m]`` (as the numpy backend's ``_Evaluator.block_sums``,
    operation for operation): J^T J (upper triangle, unknowns (a, b, rho)), J^T r, J^T P,
    P.P, P.r, r.r, with r = I - f over the usable measurements and P = df/dA. The scratch
    rows of :func:`_view_terms` must be set."""
    for i in range(N_SUMS * CHUNK):
        acc[i] = _F0
    value_floor = consts[VALUE_FLOOR]
    max_inv = _F1 / consts[DERIVATIVE_FLOOR]
    for k in range(values.shape[0]):
        _light_terms(k, j0, m, lights, intensity, phase, scr)
        for i in range(m):
            j = _U(j0 + i)
            # (Written out here and in linear_sums: an inlined helper returning a tuple keeps
            # LLVM from vectorising the loop.)
            nx, ny, nz = n[0, j], n[1, j], n[2, j]
            ci = scr[_U(_LX + i)] * nx + scr[_U(_LY + i)] * ny + scr[_U(_LZ + i)] * nz
            lit = usable[k, j] & (ci > _F0) & (scr[_U(_SEEN + i)] > _F0)
            # e p and e where lit and usable, else 0 (finite factors: a product, not a branch
            # that would keep LLVM from vectorising)
            lit_f = _F1 if lit else _F0
            g = scr[_U(_G + i)] * lit_f
            em = scr[_U(_E + i)] * lit_f
            ci = max(ci, value_floor)
            inv_ci = _F1 / ci
            q = ci / (ci + scr[_U(_CR + i)])
            big_e = _exp((inv_ci + scr[_U(_INV_CR + i)]) * neg_tau)
            p = (_F1 - big_e) * q * g  # e p S
            c = ci * em  # e c_i
            val = values[k, j]  # 0 where not usable
            rho_j = rho[j]
            pa = p * a
            u = (_F1 - q) * pa
            r = val - pa - c * rho_j
            wq = g * q * big_e * a_tau
            d_inv_cr = scr[_U(_DINV_CR + i)]
            d_inv_ci = min(inv_ci, max_inv)
            dfr = (wq * d_inv_cr + u) * d_inv_cr  # -df/dc_r
            dfi = (u - wq * d_inv_ci) * d_inv_ci + em * rho_j  # df/dc_i
            terms[_U(_J1 + i)] = (scr[_U(_LX + i)] - ci * n[0, j]) * dfi - dfr * scr[_U(_VTX + i)]
            terms[_U(_J2 + i)] = (scr[_U(_LY + i)] - ci * n[1, j]) * dfi - dfr * scr[_U(_VTY + i)]
            terms[_U(_C + i)] = c
            terms[_U(_P + i)] = p
            terms[_U(_R + i)] = r
        for i in range(m):
            j1, j2, c = terms[_U(_J1 + i)], terms[_U(_J2 + i)], terms[_U(_C + i)]
            acc[_U(_ACC[0] + i)] += j1 * j1
            acc[_U(_ACC[1] + i)] += j1 * j2
            acc[_U(_ACC[2] + i)] += j1 * c
            acc[_U(_ACC[3] + i)] += j2 * j2
            acc[_U(_ACC[4] + i)] += j2 * c
            acc[_U(_ACC[5] + i)] += c * c
        for i in range(m):
            j1, j2 = terms[_U(_J1 + i)], terms[_U(_J2 + i)]
            c, r = terms[_U(_C + i)], terms[_U(_R + i)]
            acc[_U(_ACC[6] + i)] += j1 * r
            acc[_U(_ACC[7] + i)] += j2 * r
            acc[_U(_ACC[8] + i)] += c * r
            acc[_U(_ACC[14] + i)] += r * r
        for i in range(m):
            j1, j2, c = terms[_U(_J1 + i)], terms[_U(_J2 + i)], terms[_U(_C + i)]
            p, r = terms[_U(_P + i)], terms[_U(_R + i)]
            acc[_U(_ACC[9] + i)] += j1 * p
            acc[_U(_ACC[10] + i)] += j2 * p
            acc[_U(_ACC[11] + i)] += c * p
            acc[_U(_ACC[12] + i)] += p * p
            acc[_U(_ACC[13] + i)] += p * r
    for row in range(N_SUMS):
        off = row * CHUNK
        for i in range(m):
            sums[row, _U(j0 + i)] = acc[_U(off + i)]


@serial_kernel
def _steps(j0, m, sums, lam, consts, delta0, w):
    """Damped Gauss–Newton steps of the chunk's pixels (as the numpy backend's
    ``_block_step``): delta0 = Hd^-1 J^T r, w = Hd^-1 J^T P with Hd = H + lambda diag(H)
    inverted by its adjugate (:mod:`photometric.symmetric_solve`); a (nearly) singular Hd
    gives a zero step and raises the pixel's damping."""
    up, top = consts[LAMBDA_UP], consts[LAMBDA_MAX]
    for i in range(m):
        j = _U(j0 + i)
        h11, h12, h13 = sums[0, j], sums[1, j], sums[2, j]
        h22, h23, h33 = sums[3, j], sums[4, j], sums[5, j]
        lj = lam[j]
        tiny = (h11 + h22 + h33) * _TINY_TRACE + _TINY
        d1 = h11 + lj * max(h11, tiny)
        d2 = h22 + lj * max(h22, tiny)
        d3 = h33 + lj * max(h33, tiny)
        a11, a12, a13, a22, a23, a33, det = _adjugate(d1, h12, h13, d2, h23, d3)
        ok = det > _SINGULAR * d1 * d2 * d3
        inv = _F1 / det
        inv_det = inv if ok else _F0
        raised = min(lj * up, top)
        lam[j] = lj if ok else raised  # (nearly) singular: no step, more damping next time
        g1, g2, g3 = sums[6, j], sums[7, j], sums[8, j]
        c1, c2, c3 = sums[9, j], sums[10, j], sums[11, j]
        delta0[0, j], delta0[1, j], delta0[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, g1, g2, g3)
        w[0, j], w[1, j], w[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, c1, c2, c3)


@serial_kernel
def _step_parts(j0, m, sums, delta0, w, parts, chunk):
    """The chunk's parts of the Schur complement on A into ``parts[chunk, 1:5]`` (float64):
    P.r, (J^T P).delta0, P.P, (J^T P).w."""
    ga = cd = dd = cw = 0.0
    for i in range(m):
        j = _U(j0 + i)
        c1, c2, c3 = sums[9, j], sums[10, j], sums[11, j]
        ga += float(sums[13, j])
        dd += float(sums[12, j])
        cd += float(c1 * delta0[0, j]) + float(c2 * delta0[1, j]) + float(c3 * delta0[2, j])
        cw += float(c1 * w[0, j]) + float(c2 * w[1, j]) + float(c3 * w[2, j])
    parts[chunk, 1], parts[chunk, 2], parts[chunk, 3], parts[chunk, 4] = ga, cd, dd, cw


@parallel_kernel
def linear_sums(n, values, usable, lights, views, intensity, phase, neg_tau, consts, rows,
                parts):
    """For A's and rho's joint linear fit at the normals ``n``: per pixel P.P, P.C, C.C, P.I,
    C.I into ``rows`` (5, N) float32 (P = e p S, C = e c_i over the lit usable
    measurements), and per chunk the parts of the fit's numerator sum (P.I - P.C C.I / C.C)
    and denominator sum (P.P - (P.C)^2 / C.C) into ``parts`` (chunks, 2) float64."""
    count = n.shape[1]
    value_floor = consts[VALUE_FLOOR]
    for chunk in prange(parts.shape[0]):
        j0, m = _chunk_span(chunk, count)
        scr = np.empty(_SCRATCH, np.float32)
        acc = np.zeros(5 * CHUNK, np.float32)
        _view_terms(n, j0, m, views, consts, scr)
        for k in range(values.shape[0]):
            _light_terms(k, j0, m, lights, intensity, phase, scr)
            for i in range(m):
                j = _U(j0 + i)
                # as in _model_sums
                ci = (scr[_U(_LX + i)] * n[0, j] + scr[_U(_LY + i)] * n[1, j]
                      + scr[_U(_LZ + i)] * n[2, j])
                lit = usable[k, j] & (ci > _F0) & (scr[_U(_SEEN + i)] > _F0)
                lit_f = _F1 if lit else _F0
                g = scr[_U(_G + i)] * lit_f
                em = scr[_U(_E + i)] * lit_f
                ci = max(ci, value_floor)
                q = ci / (ci + scr[_U(_CR + i)])
                p = (_F1 - _exp((_F1 / ci + scr[_U(_INV_CR + i)]) * neg_tau)) * q * g
                c = ci * em
                val = values[k, j]
                acc[_U(_ACC[0] + i)] += p * p
                acc[_U(_ACC[1] + i)] += p * c
                acc[_U(_ACC[2] + i)] += c * c
                acc[_U(_ACC[3] + i)] += p * val
                acc[_U(_ACC[4] + i)] += c * val
        for row in range(5):
            off = row * CHUNK
            for i in range(m):
                rows[row, _U(j0 + i)] = acc[_U(off + i)]
        num = den = 0.0
        for i in range(m):
            pp, pc = float(acc[_U(_ACC[0] + i)]), float(acc[_U(_ACC[1] + i)])
            cc = max(float(acc[_U(_ACC[2] + i)]), 1e-30)
            num += float(acc[_U(_ACC[3] + i)]) - pc * float(acc[_U(_ACC[4] + i)]) / cc
            den += pp - pc * pc / cc
        parts[chunk, 0] = num
        parts[chunk, 1] = den


@parallel_kernel
def start(n, rho, lam, rows, scale, a_tau, neg_tau, values, usable, lights, views, intensity,
          phase, consts, sums, delta0, w, parts):
    """rho in closed form for A = ``scale`` (float64) at the initial normals (from ``rows``
    of :func:`linear_sums`), the pixels' sums there and their first step. Per chunk into
    ``parts`` (chunks, 5) float64: the cost and the Schur parts (:func:`_step_parts`)."""
    count = n.shape[1]
    a = np.float32(scale)
    for chunk in prange(parts.shape[0]):
        j0, m = _chunk_span(chunk, count)
        scr = np.empty(_SCRATCH, np.float32)
        for i in range(m):
            j = _U(j0 + i)
            pc, cc, c_i = float(rows[1, j]), float(rows[2, j]), float(rows[4, j])
            fitted = max((c_i - scale * pc) / max(cc, 1e-30), 0.0)
            kept = float(rho[j])
            rho[j] = fitted if cc > 0.0 else kept
        _view_terms(n, j0, m, views, consts, scr)
        _model_sums(n, rho, j0, m, a, a_tau, neg_tau, values, usable, lights, intensity,
                    phase, consts, scr, np.empty(_TERMS, np.float32),
                    np.empty(N_SUMS * CHUNK, np.float32), sums)
        _steps(j0, m, sums, lam, consts, delta0, w)
        _step_parts(j0, m, sums, delta0, w, parts, chunk)
        cost = 0.0
        for i in range(m):
            cost += float(sums[14, _U(j0 + i)])
        parts[chunk, 0] = cost


@parallel_kernel
def candidate(n, rho, delta0, w, scale, trial, a_tau, neg_tau, values, usable, lights, views,
              intensity, phase, consts, sums, n_new, rho_new, sums_new, parts):
    """Each pixel's candidate for A -> ``trial`` (float64; step delta0 - (trial - A) w along
    the tangent directions and in rho), its sums at ``trial``, and the choice at ``trial``:
    per chunk into ``parts`` (chunks, 3) float64 the chosen cost, P.r and P.P."""
    count = n.shape[1]
    d_scale = trial - scale
    d32 = np.float32(d_scale)
    a = np.float32(trial)
    for chunk in prange(parts.shape[0]):
        j0, m = _chunk_span(chunk, count)
        scr = np.empty(_SCRATCH, np.float32)
        for i in range(m):
            j = _U(j0 + i)
            sa = delta0[0, j] - d32 * w[0, j]
            sb = delta0[1, j] - d32 * w[1, j]
            sr = delta0[2, j] - d32 * w[2, j]
            nx, ny, nz = n[0, j], n[1, j], n[2, j]
            # n + a t_x + b t_y, t_x = e_x - n_x n, t_y = e_y - n_y n (_tangent_axes)
            mx = nx + sa * (-nx * nx + _F1) + sb * (-ny * nx)
            my = ny + sa * (-nx * ny) + sb * (-ny * ny + _F1)
            mz = nz + sa * (-nx * nz) + sb * (-ny * nz)
            norm = np.sqrt(mx * mx + my * my + mz * mz)
            n_new[0, j] = mx / norm
            n_new[1, j] = my / norm
            n_new[2, j] = mz / norm
            rho_new[j] = max(rho[j] + sr, _F0)
        _view_terms(n_new, j0, m, views, consts, scr)
        _model_sums(n_new, rho_new, j0, m, a, a_tau, neg_tau, values, usable, lights,
                    intensity, phase, consts, scr, np.empty(_TERMS, np.float32),
                    np.empty(N_SUMS * CHUNK, np.float32), sums_new)
        cost = ga = dd = 0.0
        for i in range(m):
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


@serial_kernel
def _keep_better(j0, m, d_old, d_new, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
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
    for i in range(m):
        j = _U(j0 + i)
        old_d, old_ga, old_c = float(sums[12, j]), float(sums[13, j]), float(sums[14, j])
        new_d, new_ga = float(sums_new[12, j]), float(sums_new[13, j])
        old = old_c + d_old * (d_old * old_d - 2.0 * old_ga)
        new = float(sums_new[14, j]) + d_new * (d_new * new_d - 2.0 * new_ga)
        accept = new <= old  # never a non-finite candidate
        scr[_U(_TAKE + i)] = _F1 if accept else _F0
        chosen[i] = new if accept else old
    for row in range(N_SUMS):  # J^T J, J^T P, P.P of the kept state (the rest below)
        if 6 <= row <= 8 or row >= 13:
            continue
        for i in range(m):
            j = _U(j0 + i)
            cand, kept = sums_new[row, j], sums[row, j]
            sums[row, j] = cand if scr[_U(_TAKE + i)] > _F0 else kept
    for i in range(m):
        # J^T r, P.r, r.r of the kept state at A = at (n, rho unchanged, J kept)
        j = _U(j0 + i)
        accept = scr[_U(_TAKE + i)] > _F0
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
    for i in range(m):
        j = _U(j0 + i)
        accept = scr[_U(_TAKE + i)] > _F0
        nx, ny, nz, rho_j = n_new[0, j], n_new[1, j], n_new[2, j], rho_new[j]
        ox, oy, oz, rho_o = n[0, j], n[1, j], n[2, j], rho[j]
        n[0, j] = nx if accept else ox
        n[1, j] = ny if accept else oy
        n[2, j] = nz if accept else oz
        rho[j] = rho_j if accept else rho_o
        lj = lam[j] * (down if accept else up)
        lam[j] = min(max(lj, low), top)


@parallel_kernel
def commit(n, rho, lam, scale, trial, at, consts, sums, n_new, rho_new, sums_new, delta0, w,
           parts):
    """Each pixel keeps the better of its state and its candidate at A = ``at`` (float64;
    their sums brought to that A: r -> r - (at - A) P), adapts its damping and takes its
    next step. Per chunk into ``parts`` (chunks, 5) float64: the cost and the Schur parts
    (:func:`_step_parts`)."""
    count = n.shape[1]
    d_old, d_new = at - scale, at - trial
    for chunk in prange(parts.shape[0]):
        j0, m = _chunk_span(chunk, count)
        scr = np.empty(_SCRATCH, np.float32)
        chosen = np.empty(CHUNK)  # the chosen states' costs at A = at, float64
        _keep_better(j0, m, d_old, d_new, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
                     scr, chosen)
        _steps(j0, m, sums, lam, consts, delta0, w)
        _step_parts(j0, m, sums, delta0, w, parts, chunk)
        cost = 0.0
        for i in range(m):
            cost += chosen[i]
        parts[chunk, 0] = cost


# -- Gathering the masked pixels (the solver's _prepare, numba backend) and the result. --
# Bits of gather's ``bad`` flags: the pixel's light direction (any light) or view direction
# is not finite, or zero.
BAD_LIGHT, ZERO_LIGHT, BAD_VIEW, ZERO_VIEW = 1, 2, 4, 8


@inline_kernel
def _use(k, p, images, usable, intensity):
    """Measurement k of image pixel p: its value as float32 and whether it is usable (the
    given ``usable``, or > 0 when ``usable`` has one column; finite; per-pixel intensity
    finite and > 0)."""
    v = np.float32(images[k, p])
    u = usable[k, p] if usable.shape[1] > 1 else v > 0
    u = u and math.isfinite(v)
    if intensity.shape[1] > 1:
        e = np.float32(intensity[k, p])
        u = u and math.isfinite(e) and e > 0
    return v, u


@parallel_kernel
def select_pixels(cand, images, usable, intensity, normals, albedo, keep, counts):
    """Which of the candidate image pixels ``cand`` (N,) can be solved: a finite, non-zero
    initial normal, a finite albedo and at least 3 usable measurements (``keep`` (N,)
    bool; ``counts`` (N,) int32 the usable measurements). ``images`` (K, H*W);
    ``usable`` (K, H*W) bool, or (1, 1) for the default (> 0); ``intensity`` (K, H*W) per
    pixel or (K, 1); ``normals`` (H*W, 3); ``albedo`` (H*W,)."""
    count = cand.shape[0]
    for chunk in prange((count + CHUNK - 1) // CHUNK):
        j0, m = _chunk_span(chunk, count)
        for j in range(j0, j0 + m):
            counts[j] = 0
        for k in range(images.shape[0]):  # one light at a time: few memory streams at once
            for j in range(j0, j0 + m):
                _, u = _use(k, cand[j], images, usable, intensity)
                counts[j] += 1 if u else 0
        for j in range(j0, j0 + m):
            p = cand[j]
            nx, ny, nz = float(normals[p, 0]), float(normals[p, 1]), float(normals[p, 2])
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            good = math.isfinite(norm) and norm > 0.0 and math.isfinite(float(albedo[p]))
            keep[j] = good and counts[j] >= 3


@parallel_kernel
def gather(pix, images, usable, intensity, normals, albedo, lights, views, hg, physical,
           min_cr, values, use, inten, phase, l_dirs, v_dirs, n0, rho0, counts, bad):
    """The solvable pixels ``pix`` (N,) in the passes' layout (as the numpy backend's
    ``_prepare``, operation for operation): ``values`` (K, N) float32 (0 where not usable),
    ``use`` (K, N) bool, ``inten`` e (K, N) float32 (1 where not usable) when
    ``intensity`` is per pixel, ``l_dirs`` (3, K, N) float32 unit light directions when
    ``lights`` (K, H*W, 3) is per pixel, ``v_dirs`` (3, N) float32 unit view directions
    when ``views`` (H*W, 3) is per pixel, ``phase`` e p(c, g) (K, N) float32 when any of
    those is per pixel (else these are given, with one column, and not written), ``n0``
    (3, N) float32 unit initial normals (tilted towards the camera where v.n < ``min_cr``),
    ``rho0`` (N,) float32, ``counts`` (N,) float64 usable measurements, and ``bad`` (N,)
    uint8 (``BAD_LIGHT`` ...). ``hg`` float32 (1 + g^2, 2 g, 1 - g^2, 4 pi): the
    Henyey–Greenstein constants; ``physical``: c = -l.v (else l.v)."""
    count = pix.shape[0]
    k_count = images.shape[0]
    hg_a, hg_b, hg_num, four_pi = hg[0], hg[1], hg[2], hg[3]
    per_pixel_lights = l_dirs.shape[2] > 1
    per_pixel_views = v_dirs.shape[1] > 1
    per_pixel_intensity = inten.shape[1] > 1
    per_pixel_phase = phase.shape[1] > 1
    one = np.float32(1.0)
    for chunk in prange((count + CHUNK - 1) // CHUNK):
        j0, m = _chunk_span(chunk, count)
        # The chunk's pixels gathered, one light at a time (few memory streams at once);
        # then the arithmetic in loops over consecutive columns, which LLVM vectorises.
        for j in range(j0, j0 + m):
            p = pix[j]
            counts[j] = 0.0
            rho0[j] = albedo[p]
            if per_pixel_views:
                v_dirs[0, j], v_dirs[1, j], v_dirs[2, j] = views[p, 0], views[p, 1], views[p, 2]
        for k in range(k_count):
            for j in range(j0, j0 + m):
                p = pix[j]
                v, u = _use(k, p, images, usable, intensity)
                use[k, j] = u
                values[k, j] = v if u else np.float32(0.0)
                counts[j] += 1.0 if u else 0.0
                if per_pixel_intensity:
                    inten[k, j] = np.float32(intensity[k, p]) if u else one
                if per_pixel_lights:
                    l_dirs[0, k, j] = lights[k, p, 0]
                    l_dirs[1, k, j] = lights[k, p, 1]
                    l_dirs[2, k, j] = lights[k, p, 2]
        for j in range(j0, j0 + m):
            bad[_U(j)] = 0
        if per_pixel_views:  # unit view directions (as _unit_columns)
            for j in range(j0, j0 + m):
                j = _U(j)
                vx, vy, vz = v_dirs[0, j], v_dirs[1, j], v_dirs[2, j]
                norm = vx * vx
                norm += vy * vy
                norm += vz * vz
                norm = np.sqrt(norm)
                finite = norm - norm == 0  # (not inf, not nan)
                flag = 0 if finite else BAD_VIEW
                flag = flag if norm != 0 else ZERO_VIEW
                bad[j] = bad[j] | np.uint8(flag)
                v_dirs[0, j], v_dirs[1, j], v_dirs[2, j] = vx / norm, vy / norm, vz / norm
        for k in range(k_count):
            if per_pixel_lights:  # unit light directions (as _unit_columns)
                for j in range(j0, j0 + m):
                    j = _U(j)
                    lx, ly, lz = l_dirs[0, k, j], l_dirs[1, k, j], l_dirs[2, k, j]
                    norm = lx * lx
                    norm += ly * ly
                    norm += lz * lz
                    norm = np.sqrt(norm)
                    finite = norm - norm == 0
                    flag = 0 if finite else BAD_LIGHT
                    flag = flag if norm != 0 else ZERO_LIGHT
                    bad[j] = bad[j] | np.uint8(flag)
                    l_dirs[0, k, j], l_dirs[1, k, j] = lx / norm, ly / norm
                    l_dirs[2, k, j] = lz / norm
            if per_pixel_phase:  # e p(c, g) (as henyey_greenstein)
                for j in range(j0, j0 + m):
                    jl = _U(j) if per_pixel_lights else _U(0)
                    jv = _U(j) if per_pixel_views else _U(0)
                    je = _U(j) if per_pixel_intensity else _U(0)
                    c_phi = l_dirs[0, k, jl] * v_dirs[0, jv]
                    c_phi += l_dirs[1, k, jl] * v_dirs[1, jv]
                    c_phi += l_dirs[2, k, jl] * v_dirs[2, jv]
                    c_sc = -c_phi if physical else c_phi
                    c_sc = min(max(c_sc, -one), one)
                    denom = hg_a - hg_b * c_sc
                    phase[k, _U(j)] = inten[k, je] * (hg_num / (four_pi * denom * np.sqrt(denom)))
        for j in range(j0, j0 + m):  # unit initial normals, tilted towards the camera
            p = pix[j]
            nx, ny, nz = float(normals[p, 0]), float(normals[p, 1]), float(normals[p, 2])
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx / norm, ny / norm, nz / norm
            jv = j if per_pixel_views else 0
            fx, fy, fz = float(v_dirs[0, jv]), float(v_dirs[1, jv]), float(v_dirs[2, jv])
            cr = fx * nx
            cr += fy * ny
            cr += fz * nz
            if cr < min_cr:  # facing away from the camera
                nx += (min_cr - cr) * fx
                ny += (min_cr - cr) * fy
                nz += (min_cr - cr) * fz
                norm = math.sqrt(nx * nx + ny * ny + nz * nz)
                nx, ny, nz = nx / norm, ny / norm, nz / norm
            n0[0, j], n0[1, j], n0[2, j] = nx, ny, nz


@parallel_kernel
def finish(pix, n, rho, sums, counts, normals, albedo, rms, valid):
    """The result images (flat, zeros where not valid; as the numpy backend): a pixel is
    valid if its normal and albedo are finite and its 3x3 J^T J is non-singular (its
    solution is determined); ``rms`` = sqrt(r.r / counts)."""
    count = pix.shape[0]
    for chunk in prange((count + CHUNK - 1) // CHUNK):
        j0, m = _chunk_span(chunk, count)
        for j in range(j0, j0 + m):
            h11, h12, h13 = float(sums[0, j]), float(sums[1, j]), float(sums[2, j])
            h22, h23, h33 = float(sums[3, j]), float(sums[4, j]), float(sums[5, j])
            det = _adjugate(h11, h12, h13, h22, h23, h33)[6]
            ok = (det > 1e-9 * h11 * h22 * h33 and math.isfinite(n[0, j])
                  and math.isfinite(n[1, j]) and math.isfinite(n[2, j])
                  and math.isfinite(rho[j]))
            if ok:
                p = pix[j]
                normals[p, 0], normals[p, 1], normals[p, 2] = n[0, j], n[1, j], n[2, j]
                albedo[p] = rho[j]
                rms[p] = math.sqrt(max(float(sums[14, j]), 0.0) / counts[j])
                valid[p] = True


# After an edit of a module whose functions the kernels inline (symmetric_solve), the
# cached kernels are compiled anew.
drop_stale_caches(globals())
