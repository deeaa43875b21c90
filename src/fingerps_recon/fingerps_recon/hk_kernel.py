"""Compiled (numba) per-pixel kernels of the HK solver (:mod:`fingerps_recon.hk_solver`).

The same Levenberg–Marquardt algorithm as the solver's numpy backend -- the same residual,
Jacobian, damping, accept/reject and Schur-complement step for the global scale A (see
:mod:`fingerps_recon.hk_solver`) -- with each pass over the pixels fused into one loop: per
pixel the model, its Jacobian and the 15 Gauss–Newton sums are formed in registers, over the
pixel's K measurements, and the per-pixel step is taken in the same loop. Each kernel
returns its per-pixel results in place and its parts of the global sums (A's fit, the
Schur complement, the total cost) per chunk of ``CHUNK`` pixels; the caller adds the chunks
up in a fixed order, so the result does not depend on the number of threads.

Arithmetic: float64 within a pixel; the per-pixel state and sums are stored as float32 as
in the numpy backend. The measurements and constants are read in the layout of the
solver's columns: ``values`` and ``usable`` (K, N); ``lights`` (3, K, N) or (3, K, 1);
``views`` (3, N) or (3, 1); ``intensity`` and ``phase`` (e_k and e_k p(c, g)) (K, N) or
(K, 1). The state is pixel-major: normals (N, 3), sums (N, 15) (rows as the solver's
``_H11`` ... ``_COST``).

Importing this module needs numba; it raises ImportError otherwise (the solver then uses
its numpy backend). The compiled code is cached on disk (``cache=True``: in the package's
``__pycache__``, else the user's cache directory, or ``NUMBA_CACHE_DIR`` when set); where no
cache directory is writable, the kernels are compiled in every process.
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np
from numba import prange

# Pixels per chunk of the parallel loops (and of the per-chunk partial sums).
CHUNK = 1024
# Indices into the ``consts`` array every kernel takes (float64).
VALUE_FLOOR, DERIVATIVE_FLOOR, LAMBDA_DOWN, LAMBDA_UP, LAMBDA_MIN, LAMBDA_MAX = range(6)
N_CONSTS = 6
N_SUMS = 15


def _jit(fn):
    """``numba.njit(parallel=True, fastmath=False, cache=True)``, without the on-disk cache
    where numba finds no writable cache directory."""
    options = {"parallel": True, "fastmath": False, "nogil": True}
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError as exc:  # "cannot cache function ...: no locator available"
        warnings.warn(f"HK kernel {fn.__name__} is not cached on disk ({exc}); set "
                      "NUMBA_CACHE_DIR to a writable directory to cache it", stacklevel=2)
        return numba.njit(cache=False, **options)(fn)


def _inline(fn):
    """A serial helper called from the kernels (compiled into them)."""
    return numba.njit(cache=True, fastmath=False, nogil=True, inline="always")(fn)


@_inline
def _column(j: int, array: np.ndarray) -> int:
    """Index of pixel j's column in an array with one column per pixel or one for all."""
    return j if array.shape[-1] > 1 else 0


@_inline
def _pixel_sums(
    j, nx, ny, nz, rho, a, tau, values, usable, lights, views, intensity, phase, consts,
):
    """The 15 Gauss–Newton sums of pixel j at normal n, albedo rho and scale A (as the numpy
    backend's ``_Evaluator.block_sums``): J^T J (upper triangle, unknowns (a, b, rho)),
    J^T r, J^T P, P.P, P.r, r.r, with r = I - f over the usable measurements, P = df/dA."""
    value_floor = consts[VALUE_FLOOR]
    max_inv = 1.0 / consts[DERIVATIVE_FLOOR]
    jl, jv = _column(j, lights), _column(j, views)
    je, jp = _column(j, intensity), _column(j, phase)
    vx, vy, vz = float(views[0, jv]), float(views[1, jv]), float(views[2, jv])
    cr_raw = vx * nx + vy * ny + vz * nz
    seen = cr_raw > 0.0
    cr = max(cr_raw, value_floor)
    inv_cr = 1.0 / cr
    d_inv_cr = min(inv_cr, max_inv)
    vtx = vx - cr * nx  # v . t_x, v . t_y for the tangent directions t = e - n_axis n
    vty = vy - cr * ny
    h11 = h12 = h13 = h22 = h23 = h33 = 0.0
    g1 = g2 = g3 = c1 = c2 = c3 = dd = ga = cost = 0.0
    for k in range(values.shape[0]):
        if not usable[k, j]:
            continue
        val = float(values[k, j])
        lx, ly, lz = float(lights[0, k, jl]), float(lights[1, k, jl]), float(lights[2, k, jl])
        ci = lx * nx + ly * ny + lz * nz
        if not (seen and ci > 0.0):  # attached shadow: f = 0, J = 0
            cost += val * val
            continue
        ci = max(ci, value_floor)
        g = float(phase[k, jp])  # e p(c, g)
        em = float(intensity[k, je])  # e
        inv_ci = 1.0 / ci
        q = ci / (ci + cr)
        big_e = math.exp(-tau * (inv_ci + inv_cr))
        p = (1.0 - big_e) * q * g  # e p S
        c = ci * em  # e c_i
        pa = a * p
        u = (1.0 - q) * pa
        r = val - pa - rho * c
        wq = g * q * big_e * (a * tau)
        d_inv_ci = min(inv_ci, max_inv)
        dfr = (wq * d_inv_cr + u) * d_inv_cr  # -df/dc_r
        dfi = (u - wq * d_inv_ci) * d_inv_ci + em * rho  # df/dc_i
        j1 = (lx - ci * nx) * dfi - dfr * vtx
        j2 = (ly - ci * ny) * dfi - dfr * vty
        h11 += j1 * j1
        h12 += j1 * j2
        h13 += j1 * c
        h22 += j2 * j2
        h23 += j2 * c
        h33 += c * c
        g1 += j1 * r
        g2 += j2 * r
        g3 += c * r
        c1 += j1 * p
        c2 += j2 * p
        c3 += c * p
        dd += p * p
        ga += p * r
        cost += r * r
    return h11, h12, h13, h22, h23, h33, g1, g2, g3, c1, c2, c3, dd, ga, cost


@_inline
def _store(sums, j, s):
    for i in range(N_SUMS):
        sums[j, i] = s[i]


@_inline
def _step(sums, j, lam, delta0, w, consts):
    """Damped Gauss–Newton step of pixel j (as the numpy backend's ``_block_step``), from
    its stored sums: delta0 = Hd^-1 J^T r and w = Hd^-1 J^T P into ``delta0[j]``, ``w[j]``,
    with Hd = H + lambda diag(H); a (nearly) singular Hd gives a zero step and raises the
    damping. Returns the pixel's parts of the Schur complement on A:
    (P.r, (J^T P).delta0, P.P, (J^T P).w)."""
    h11, h12, h13 = float(sums[j, 0]), float(sums[j, 1]), float(sums[j, 2])
    h22, h23, h33 = float(sums[j, 3]), float(sums[j, 4]), float(sums[j, 5])
    g1, g2, g3 = float(sums[j, 6]), float(sums[j, 7]), float(sums[j, 8])
    c1, c2, c3 = float(sums[j, 9]), float(sums[j, 10]), float(sums[j, 11])
    lj = float(lam[j])
    tiny = (h11 + h22 + h33) * 1e-7 + 1e-30
    d1 = h11 + lj * max(h11, tiny)
    d2 = h22 + lj * max(h22, tiny)
    d3 = h33 + lj * max(h33, tiny)
    a11 = d2 * d3 - h23 * h23
    a12 = h13 * h23 - h12 * d3
    a13 = h12 * h23 - h13 * d2
    a22 = d1 * d3 - h13 * h13
    a23 = h12 * h13 - d1 * h23
    a33 = d1 * d2 - h12 * h12
    det = d1 * a11 + h12 * a12 + h13 * a13
    inv_det = 0.0
    if det > 1e-6 * d1 * d2 * d3:
        inv_det = 1.0 / det
    else:  # (nearly) singular: no step now, more damping next time
        lam[j] = min(lj * consts[LAMBDA_UP], consts[LAMBDA_MAX])
    s1 = (a11 * g1 + a12 * g2 + a13 * g3) * inv_det
    s2 = (a12 * g1 + a22 * g2 + a23 * g3) * inv_det
    s3 = (a13 * g1 + a23 * g2 + a33 * g3) * inv_det
    w1 = (a11 * c1 + a12 * c2 + a13 * c3) * inv_det
    w2 = (a12 * c1 + a22 * c2 + a23 * c3) * inv_det
    w3 = (a13 * c1 + a23 * c2 + a33 * c3) * inv_det
    delta0[j, 0], delta0[j, 1], delta0[j, 2] = s1, s2, s3
    w[j, 0], w[j, 1], w[j, 2] = w1, w2, w3
    # Rounded as stored (float32), as the numpy backend sums them.
    s1, s2, s3 = float(delta0[j, 0]), float(delta0[j, 1]), float(delta0[j, 2])
    w1, w2, w3 = float(w[j, 0]), float(w[j, 1]), float(w[j, 2])
    return (
        float(sums[j, 13]), c1 * s1 + c2 * s2 + c3 * s3, float(sums[j, 12]),
        c1 * w1 + c2 * w2 + c3 * w3,
    )


@_inline
def _shifted_cost(sums, j, delta):
    """Pixel j's cost after A -> A + delta (the cost is quadratic in A)."""
    cost = float(sums[j, 14])
    if delta != 0.0:
        cost += delta * (delta * float(sums[j, 12]) - 2.0 * float(sums[j, 13]))
    return cost


@_jit
def linear_sums(n, values, usable, lights, views, intensity, phase, tau, consts, rows, parts):
    """For A's and rho's joint linear fit at the normals ``n`` (N, 3): per pixel
    (P.C, C.C, C.I) into ``rows`` (N, 3) float64, and per chunk the parts of the fit's
    numerator sum (P.I - P.C C.I / C.C) and denominator sum (P.P - (P.C)^2 / C.C) into
    ``parts`` (chunks, 2)."""
    count = n.shape[0]
    value_floor = consts[VALUE_FLOOR]
    for chunk in prange(parts.shape[0]):
        num = 0.0
        den = 0.0
        for j in range(chunk * CHUNK, min((chunk + 1) * CHUNK, count)):
            nx, ny, nz = float(n[j, 0]), float(n[j, 1]), float(n[j, 2])
            jl, jv = _column(j, lights), _column(j, views)
            je, jp = _column(j, intensity), _column(j, phase)
            cr = float(views[0, jv]) * nx + float(views[1, jv]) * ny + float(views[2, jv]) * nz
            seen = cr > 0.0
            cr = max(cr, value_floor)
            inv_cr = 1.0 / cr
            pp = pc = cc = p_i = c_i = 0.0
            for k in range(values.shape[0]):
                if not usable[k, j]:
                    continue
                ci = (float(lights[0, k, jl]) * nx + float(lights[1, k, jl]) * ny
                      + float(lights[2, k, jl]) * nz)
                if not (seen and ci > 0.0):
                    continue
                ci = max(ci, value_floor)
                val = float(values[k, j])
                q = ci / (ci + cr)
                p = (1.0 - math.exp(-tau * (1.0 / ci + inv_cr))) * q * float(phase[k, jp])
                c = ci * float(intensity[k, je])
                pp += p * p
                pc += p * c
                cc += c * c
                p_i += p * val
                c_i += c * val
            rows[j, 0], rows[j, 1], rows[j, 2] = pc, cc, c_i
            cc_floor = max(cc, 1e-30)
            num += p_i - pc * c_i / cc_floor
            den += pp - pc * pc / cc_floor
        parts[chunk, 0] = num
        parts[chunk, 1] = den


@_jit
def start(n, rho, lam, rows, scale, tau, values, usable, lights, views, intensity, phase, consts,
          sums, delta0, w, parts):
    """rho in closed form for A = ``scale`` at the initial normals (from ``rows`` of
    :func:`linear_sums`), the pixels' sums there and their first step. Per chunk into
    ``parts`` (chunks, 5): the cost and the Schur parts of :func:`_step`."""
    count = n.shape[0]
    for chunk in prange(parts.shape[0]):
        acc = np.zeros(5)
        for j in range(chunk * CHUNK, min((chunk + 1) * CHUNK, count)):
            pc, cc, c_i = rows[j, 0], rows[j, 1], rows[j, 2]
            if cc > 0.0:
                rho[j] = max((c_i - scale * pc) / max(cc, 1e-30), 0.0)
            s = _pixel_sums(j, float(n[j, 0]), float(n[j, 1]), float(n[j, 2]), float(rho[j]),
                            scale, tau, values, usable, lights, views, intensity, phase,
                            consts)
            _store(sums, j, s)
            acc[0] += float(sums[j, 14])
            schur = _step(sums, j, lam, delta0, w, consts)
            for i in range(4):
                acc[i + 1] += schur[i]
        for i in range(5):
            parts[chunk, i] = acc[i]


@_jit
def candidate(n, rho, delta0, w, scale, trial, tau, values, usable, lights, views, intensity,
              phase, consts, sums, n_new, rho_new, sums_new, parts):
    """Each pixel's candidate for A -> ``trial`` (step delta0 - (trial - A) w along the
    tangent directions and in rho), its sums at ``trial``, and the choice at ``trial``: per
    chunk into ``parts`` (chunks, 3) the chosen cost, P.r and P.P (for A's closed form)."""
    count = n.shape[0]
    d_scale = trial - scale
    for chunk in prange(parts.shape[0]):
        cost_sum = 0.0
        ga_sum = 0.0
        d_sum = 0.0
        for j in range(chunk * CHUNK, min((chunk + 1) * CHUNK, count)):
            sa, sb, sr = float(delta0[j, 0]), float(delta0[j, 1]), float(delta0[j, 2])
            if d_scale != 0.0:
                sa -= d_scale * float(w[j, 0])
                sb -= d_scale * float(w[j, 1])
                sr -= d_scale * float(w[j, 2])
            nx, ny, nz = float(n[j, 0]), float(n[j, 1]), float(n[j, 2])
            # n + a t_x + b t_y with t_x = e_x - n_x n, t_y = e_y - n_y n, normalised
            along = sa * nx + sb * ny
            mx = nx + sa - along * nx
            my = ny + sb - along * ny
            mz = nz - along * nz
            norm = math.sqrt(mx * mx + my * my + mz * mz)
            n_new[j, 0], n_new[j, 1], n_new[j, 2] = mx / norm, my / norm, mz / norm
            rho_new[j] = max(float(rho[j]) + sr, 0.0)
            s = _pixel_sums(j, float(n_new[j, 0]), float(n_new[j, 1]), float(n_new[j, 2]),
                            float(rho_new[j]), trial, tau, values, usable, lights, views,
                            intensity, phase, consts)
            _store(sums_new, j, s)
            old = _shifted_cost(sums, j, d_scale)
            new = float(sums_new[j, 14])
            if new <= old:
                cost_sum += new
                ga_sum += float(sums_new[j, 13])
                d_sum += float(sums_new[j, 12])
            else:
                cost_sum += old
                ga_sum += float(sums[j, 13]) - d_scale * float(sums[j, 12])
                d_sum += float(sums[j, 12])
        parts[chunk, 0] = cost_sum
        parts[chunk, 1] = ga_sum
        parts[chunk, 2] = d_sum


@_jit
def commit(n, rho, lam, scale, trial, at, consts, sums, n_new, rho_new, sums_new, delta0, w,
           parts):
    """Each pixel keeps the better of its state and its candidate at A = ``at`` (their sums
    brought to that A), adapts its damping and takes its next step. Per chunk into
    ``parts`` (chunks, 5): the cost and the Schur parts of :func:`_step`."""
    count = n.shape[0]
    d_old = at - scale
    d_new = at - trial
    for chunk in prange(parts.shape[0]):
        acc = np.zeros(5)
        for j in range(chunk * CHUNK, min((chunk + 1) * CHUNK, count)):
            old = _shifted_cost(sums, j, d_old)
            new = _shifted_cost(sums_new, j, d_new)
            if new <= old:  # take the candidate (a non-finite one never)
                src, delta = sums_new, d_new
                n[j, 0], n[j, 1], n[j, 2] = n_new[j, 0], n_new[j, 1], n_new[j, 2]
                rho[j] = rho_new[j]
                lj = float(lam[j]) * consts[LAMBDA_DOWN]
                acc[0] += new
            else:
                src, delta = sums, d_old
                lj = float(lam[j]) * consts[LAMBDA_UP]
                acc[0] += old
            lam[j] = min(max(lj, consts[LAMBDA_MIN]), consts[LAMBDA_MAX])
            # The kept sums at A = at (n, rho unchanged, J kept): r -> r - delta P.
            dd, ga = float(src[j, 12]), float(src[j, 13])
            cost = float(src[j, 14])
            g1, g2, g3 = float(src[j, 6]), float(src[j, 7]), float(src[j, 8])
            if delta != 0.0:
                cost += delta * (delta * dd - 2.0 * ga)
                g1 -= delta * float(src[j, 9])
                g2 -= delta * float(src[j, 10])
                g3 -= delta * float(src[j, 11])
                ga -= delta * dd
            for i in range(6):
                sums[j, i] = src[j, i]
            sums[j, 6], sums[j, 7], sums[j, 8] = g1, g2, g3
            for i in range(9, 13):
                sums[j, i] = src[j, i]
            sums[j, 13], sums[j, 14] = ga, cost
            schur = _step(sums, j, lam, delta0, w, consts)
            for i in range(4):
                acc[i + 1] += schur[i]
        for i in range(5):
            parts[chunk, i] = acc[i]
