"""Compiled (numba) passes of the HK solver (:mod:`photometric.hk_solver`): paper Eq. 4, 6-7.

Per chunk of ``CHUNK`` pixels (``prange`` over the chunks, one chunk per thread at a time)
the model of Eq. 4, its Jacobian and the 15 Gauss–Newton sums of every pixel are formed
light by light while the chunk's sums stay in the core's L1 cache, the step is taken in
the same pass, and nothing of size (K, N) is written. The global sums (A's fit, the Schur
complement, the total cost) are returned per chunk in float64 and added up by the caller
in a fixed order, so the result does not depend on the number of threads. With A held
(:func:`solve_held`) the pixels need no global sum between iterations, and one pass does
the whole solve of each chunk, its measurements and state in the core's cache
(L1/L2), from the gathering to the result images.

Layout.

- The lighting, which depends on the calibration only (:func:`lighting_terms`, once per
  calibration and camera): per prepared pixel q and light k, ``terms`` (K, N_TERMS, Q)
  float32 rows ``LX, LY, LZ`` (the unit light direction), ``G`` (e_k p(c, g)) and ``E``
  (e_k; 0 where the intensity is not usable); ``views`` (3, Q) the unit view directions;
  ``bad`` (Q,) flags of non-finite or zero directions.
- A burst (:func:`gather`): the N pixels of its mask, padded to
  ``chunks * CHUNK`` (padding pixels and those that cannot be solved have no usable
  measurement, normal (0, 0, 1) and albedo 0: their sums are zero, they take no step and
  add nothing to the global sums),
  so that every loop over a chunk has the constant trip count ``CHUNK``. ``meas``
  (chunks, K, N_MEAS, CHUNK) float32: per chunk and light one contiguous block of the
  lighting rows and ``VALUE`` (I), with G, E and I zero where the measurement is not
  usable -- so that an unusable measurement adds exactly nothing to any sum, and a pass
  reads one sequential stream. Views (3, Np), the state component-major: normals
  (3, Np), sums (15, Np) with rows ``_H11`` ... ``_COST`` of the solver. Scalars: ``a``
  (A), ``a_tau`` (A tau_d) and ``neg_tau`` (-tau_d) as float32; ``consts`` float32
  (indices below).

Vectorisation (LLVM, 8 float32 lanes with AVX2, 16 with AVX-512): the loops over a
chunk's pixels have no calls and no branches -- min/max are written as selects
(:func:`_fmax`, :func:`_fmin`: numba's builtin ``min``/``max`` on floats keep LLVM from
vectorising a loop), exp() is inlined arithmetic (:func:`_exp`, relative error < 4e-6)
whose power of two is a bit cast (:func:`_int_bits_as_float`) -- and unit strides.

The compiled code is cached on disk (``cache=True``: in the package's ``__pycache__``, else
the user's cache directory, or ``NUMBA_CACHE_DIR`` when set); where no cache directory is
writable the kernels are compiled in every process (a warning says so).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba import prange
from numba.extending import intrinsic

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    parallel_kernel,
    serial_kernel,
)
from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64

# Pixels per chunk of the parallel loops (the chunk's scratch arrays stay in L1/L2).
CHUNK = 256
# Indices into ``consts`` (float32).
VALUE_FLOOR, DERIVATIVE_FLOOR, LAMBDA_DOWN, LAMBDA_UP, LAMBDA_MIN, LAMBDA_MAX = range(6)
N_CONSTS = 6
N_SUMS = 15
# Rows of the lighting terms of a light (``terms[k]``) and of a chunk's block of
# measurements of one light (``meas[chunk, k]``: the same rows, then the value).
LX, LY, LZ, G, E, VALUE = range(6)
N_TERMS = 5
N_MEAS = 6
# Bits of ``bad``: the pixel's light direction (any light) or view direction is not finite,
# or zero.
BAD_LIGHT, ZERO_LIGHT, BAD_VIEW, ZERO_VIEW = 1, 2, 4, 8
# Offsets of the rows of a chunk's scratch (indexed _U(offset + i), rows CHUNK apart):
# c_r (floored), 1/c_r, the capped 1/c_r of the derivatives, v.t_x, v.t_y, whether
# v.n > 0 (1 or 0), and the commit's choice (1 or 0).
_CR, _INV_CR, _DINV_CR, _VTX, _VTY, _SEEN, _TAKE = (row * CHUNK for row in range(7))
_SCRATCH = 7 * CHUNK
_ACC = tuple(row * CHUNK for row in range(N_SUMS))

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)
_HALF = np.float32(0.5)
_TINY_TRACE = np.float32(1e-7)
_TINY = np.float32(1e-30)
_SINGULAR = np.float32(1e-6)
# exp(x) for float32 x: 2^n e^r, |r| <= ln2 / 2, e^r by the degree-4 polynomial that
# interpolates it at the Chebyshev points of that interval (relative error < 4e-6 in
# float32, measured on a grid of 200 001 points); below _EXP_LO (e^x < 1.2e-38, the
# smallest normal float32) it returns 1.2e-38.
_EXP_LO = np.float32(-87.33)
_LOG2E = np.float32(1.44269504088896341)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EXP_P = tuple(np.float32(c) for c in (
    0.9999999999999998, 0.9999622946507603, 0.499993721386277, 0.16792143016520872,
    0.04187564445213479,
))
_P0, _P1, _P2, _P3, _P4 = _EXP_P
_BIAS = np.int32(127)
_MANTISSA = np.int32(23)


# The symmetric 3x3 solve by the adjugate (photometric.symmetric_solve), inlined.
_adjugate = inline_kernel(symmetric_adjugate)
_adjugate_solve = inline_kernel(adjugate_solve)


@intrinsic
def _int_bits_as_float(typingctx, bits):
    """The float32 whose bits are the int32 ``bits`` (an LLVM bit cast, which vectorises;
    ``np.int32(bits).view(np.float32)`` does not)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return numba.float32(numba.int32), codegen


@inline_kernel
def _fmax(a, b):
    """max(a, b) as a select (NaN in ``a`` propagates)."""
    return b if a < b else a


@inline_kernel
def _fmin(a, b):
    """min(a, b) as a select (NaN in ``a`` propagates)."""
    return b if a > b else a


@inline_kernel
def _exp(x):
    """exp(x), float32, relative error < 4e-6 for -87.33 <= x <= 88 (branch-free, inlined).
    In the model it multiplies terms below 3e-4 of the single-scattering term for the
    finger's skin constants (``hk_solver``), so its error is below 1.2e-9 of that term."""
    x = _fmax(x, _EXP_LO)
    fn = np.floor(x * _LOG2E + _HALF)
    r = x - fn * _LN2_HI
    r = r - fn * _LN2_LO
    poly = (((_P4 * r + _P3) * r + _P2) * r + _P1) * r + _P0
    return poly * _int_bits_as_float((np.int32(fn) + _BIAS) << _MANTISSA)  # poly 2^fn


# -- The lighting of a calibration, and a burst's pixels in the passes' layout. --

@parallel_kernel
def lighting_terms(pixels, lights, views, intensity, hg, physical, terms, v_out, bad):
    """The lighting of the image pixels ``pixels`` (Q,) (the module docstring): ``terms``
    (K, N_TERMS, Q) float32, ``v_out`` (3, Q) float32 and ``bad`` (Q,) uint8. ``lights``
    (K, H*W, 3) per pixel or (K, 1, 3); ``views`` (H*W, 3) per pixel or (1, 3);
    ``intensity`` (K, H*W) per pixel or (K, 1) (a measurement whose e is not finite or
    <= 0 is left out: E = G = 0); ``hg`` float32 (1 + g^2, 2 g, 1 - g^2, 4 pi): the
    Henyey–Greenstein constants; ``physical``: the scattering cosine is -l.v (else l.v)."""
    count = pixels.shape[0]
    k_count = terms.shape[0]
    hg_a, hg_b, hg_num, four_pi = hg[0], hg[1], hg[2], hg[3]
    per_pixel_lights = lights.shape[1] > 1
    per_pixel_views = views.shape[0] > 1
    per_pixel_intensity = intensity.shape[1] > 1
    one, zero = np.float32(1.0), np.float32(0.0)
    for chunk in prange((count + CHUNK - 1) // CHUNK):
        for q in range(chunk * CHUNK, min(chunk * CHUNK + CHUNK, count)):
            p = pixels[q]
            pv = p if per_pixel_views else 0
            vx, vy, vz = (np.float32(views[pv, 0]), np.float32(views[pv, 1]),
                          np.float32(views[pv, 2]))
            norm = np.sqrt(vx * vx + vy * vy + vz * vz)
            flag = 0 if norm - norm == 0 else BAD_VIEW  # (not inf, not nan)
            flag = flag if norm != 0 else ZERO_VIEW
            vx, vy, vz = vx / norm, vy / norm, vz / norm
            v_out[0, q], v_out[1, q], v_out[2, q] = vx, vy, vz
            pl = p if per_pixel_lights else 0
            pe = p if per_pixel_intensity else 0
            for k in range(k_count):
                lx = np.float32(lights[k, pl, 0])
                ly = np.float32(lights[k, pl, 1])
                lz = np.float32(lights[k, pl, 2])
                norm = np.sqrt(lx * lx + ly * ly + lz * lz)
                lflag = 0 if norm - norm == 0 else BAD_LIGHT
                flag |= lflag if norm != 0 else ZERO_LIGHT
                lx, ly, lz = lx / norm, ly / norm, lz / norm
                e = np.float32(intensity[k, pe])
                usable = math.isfinite(e) and e > 0
                c_phi = lx * vx + ly * vy + lz * vz
                c_sc = -c_phi if physical else c_phi
                c_sc = _fmin(_fmax(c_sc, -one), one)
                denom = hg_a - hg_b * c_sc
                phase = hg_num / (four_pi * denom * np.sqrt(denom))
                terms[k, LX, q], terms[k, LY, q], terms[k, LZ, q] = lx, ly, lz
                terms[k, G, q] = e * phase if usable else zero
                terms[k, E, q] = e if usable else zero
            bad[q] = np.uint8(flag)


@parallel_kernel
def gather(cand, index, images, usable, normals, albedo, terms, views, bad, min_cr, meas,
           v_dirs, n0, rho0, solved, counts, flags):
    """The mask's pixels ``cand`` (N,) (increasing image indices) in the passes' layout,
    padded to ``chunks * CHUNK`` (the module docstring): ``meas`` (chunks, K, N_MEAS, CHUNK)
    float32, ``v_dirs`` (3, Np), ``n0`` (3, Np), ``rho0`` (Np,), ``counts``, ``solved`` and
    ``flags`` (chunks,) uint8 as :func:`_gather_chunk` fills them, chunk by chunk."""
    for chunk in prange(meas.shape[0]):
        flags[chunk] = _gather_chunk(chunk, cand, index, images, usable, normals, albedo,
                                     terms, views, bad, min_cr, meas[chunk], v_dirs, n0,
                                     rho0, chunk * CHUNK, solved, counts)


@serial_kernel
def _gather_chunk(chunk, cand, index, images, usable, normals, albedo, terms, views, bad,
                  min_cr, block_meas, v_dirs, n0, rho0, d0, solved, counts):
    """The chunk ``chunk`` of the mask's pixels ``cand`` (N,) (increasing image indices),
    padded to ``CHUNK`` pixels: ``block_meas`` (K, N_MEAS, CHUNK) float32, and the columns
    ``d0 .. d0 + CHUNK`` of ``v_dirs`` (3, .) float32, ``n0`` (3, .) float32 unit initial
    normals (tilted towards the camera where v.n < ``min_cr``) and ``rho0`` (.,) float32;
    at the candidates' own indices, ``counts`` (N,) float64 the usable measurements and
    ``solved`` (N,) bool the pixels that can be solved -- a finite, non-zero initial
    normal, a finite albedo, at least 3 usable measurements; the others get no usable
    measurement. Returns the ``bad`` bits of the chunk's solved pixels. ``index`` (H*W,)
    int64 each image pixel's lighting column (every candidate has one); ``images`` (K, H*W);
    ``usable`` (K, H*W) bool (a measurement is usable where it is True, its value finite
    and its E > 0); ``normals`` (H*W, 3); ``albedo`` (H*W,); ``terms``, ``views``, ``bad``
    the lighting (:func:`lighting_terms`).

    The chunk's pixels are copied run by run (consecutive image pixels have consecutive
    lighting columns), so the copies are contiguous loops that LLVM vectorises."""
    count = cand.shape[0]
    k_count = images.shape[0]
    zero, one = np.float32(0.0), np.float32(1.0)
    j0 = chunk * CHUNK
    m = min(j0 + CHUNK, count) - j0
    starts = np.empty(CHUNK + 1, np.int64)  # the runs: [starts[r], starts[r + 1])
    runs = 0
    for i in range(m):
        if i == 0 or cand[j0 + i] != cand[j0 + i - 1] + 1:
            starts[runs] = i
            runs += 1
    starts[runs] = m
    taken = np.empty(CHUNK, np.float32)  # 1 where the light's measurement is usable
    count = np.zeros(CHUNK, np.float32)  # usable measurements so far (exact integers)
    # Loops that each write one or two arrays, with unsigned indices, so that LLVM
    # vectorises them (it checks at run time that the arrays a loop writes do not overlap
    # the others, and vectorises only below a limit of such checks).
    for k in range(k_count):
        block = block_meas[k]
        for r in range(runs):
            s0, s1 = _U(starts[r]), _U(starts[r + 1])
            p0 = cand[j0 + s0]
            q0 = _U(index[p0]) - s0
            p0 = _U(p0) - s0
            for row in range(N_TERMS):
                src = terms[k, row]
                dst = block[row]
                for i in range(s0, s1):
                    dst[_U(i)] = src[_U(q0 + i)]
            src_v = images[k]
            src_u = usable[k]
            energy = block[E]
            value = block[VALUE]
            for i in range(s0, s1):  # one array written a loop (see above)
                v = np.float32(src_v[_U(p0 + i)])
                u = src_u[_U(p0 + i)] & (v - v == zero) & (energy[_U(i)] > zero)
                taken[_U(i)] = one if u else zero
            for i in range(s0, s1):
                v = np.float32(src_v[_U(p0 + i)])
                value[_U(i)] = v if taken[_U(i)] > zero else zero
        for row in (G, E):
            dst = block[row]
            for i in range(m):
                dst[_U(i)] = dst[_U(i)] if taken[_U(i)] > zero else zero
        for i in range(m):
            count[_U(i)] += taken[_U(i)]
        for i in range(m, CHUNK):
            block[LX, i], block[LY, i], block[LZ, i] = zero, zero, one
            block[G, i], block[E, i], block[VALUE, i] = zero, zero, zero
    for i in range(m):
        counts[j0 + i] = float(count[i])
    chunk_flags = 0
    for i in range(CHUNK):
        j = j0 + i
        d = d0 + i
        ok = False
        nx, ny, nz, rho, norm = 0.0, 0.0, 1.0, 0.0, 1.0
        vx, vy, vz = zero, zero, one
        if i < m:
            p = cand[j]
            q = index[p]
            vx, vy, vz = views[0, q], views[1, q], views[2, q]
            nx, ny, nz = float(normals[p, 0]), float(normals[p, 1]), float(normals[p, 2])
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            rho = float(albedo[p])
            ok = (counts[j] >= 3 and math.isfinite(norm) and norm > 0.0
                  and math.isfinite(rho))
            solved[j] = ok
            if ok:
                chunk_flags |= bad[q]
            else:  # not solved: no usable measurement
                for k in range(k_count):
                    block_meas[k, G, i] = zero
                    block_meas[k, E, i] = zero
                    block_meas[k, VALUE, i] = zero
        v_dirs[0, d], v_dirs[1, d], v_dirs[2, d] = vx, vy, vz
        if ok:  # unit initial normal, tilted towards the camera
            nx, ny, nz = nx / norm, ny / norm, nz / norm
            fx, fy, fz = float(vx), float(vy), float(vz)
            cr = fx * nx
            cr += fy * ny
            cr += fz * nz
            if cr < min_cr:  # facing away from the camera
                nx += (min_cr - cr) * fx
                ny += (min_cr - cr) * fy
                nz += (min_cr - cr) * fz
                norm = math.sqrt(nx * nx + ny * ny + nz * nz)
                nx, ny, nz = nx / norm, ny / norm, nz / norm
        else:
            nx, ny, nz, rho = 0.0, 0.0, 1.0, 0.0
        n0[0, d], n0[1, d], n0[2, d] = nx, ny, nz
        rho0[d] = rho
    return np.uint8(chunk_flags)


@serial_kernel
def _view_terms(n, views, j0, consts, scr):
    """Per pixel of the chunk at ``j0``: c_r = v.n (floored), 1/c_r, the capped 1/c_r of the
    derivatives, v.t_x, v.t_y for the tangent directions t = e - n_axis n, and whether
    v.n > 0 (1 or 0), into the scratch."""
    value_floor = consts[VALUE_FLOOR]
    derivative_floor = consts[DERIVATIVE_FLOOR]
    for i in range(CHUNK):
        j = _U(j0 + i)
        nx, ny, nz = n[0, j], n[1, j], n[2, j]
        vx, vy, vz = views[0, j], views[1, j], views[2, j]
        cr = vx * nx
        cr += vy * ny
        cr += vz * nz
        scr[_U(_SEEN + i)] = _F1 if cr > _F0 else _F0
        cr = _fmax(cr, value_floor)
        scr[_U(_CR + i)] = cr
        scr[_U(_INV_CR + i)] = _F1 / cr
        scr[_U(_DINV_CR + i)] = _F1 / _fmax(cr, derivative_floor)
        scr[_U(_VTX + i)] = vx - cr * nx
        scr[_U(_VTY + i)] = vy - cr * ny


@serial_kernel
def _model_sums(n, rho, chunk, a, a_tau, neg_tau, meas, consts, scr, acc, sums):
    """The 15 Gauss–Newton sums of the chunk's pixels at normals ``n``, albedo ``rho`` and
    A = ``a`` into ``sums[:, chunk * CHUNK:][:, :CHUNK]``: J^T J (upper triangle, unknowns
    (a, b, rho)), J^T r, J^T P, P.P, P.r, r.r, with r = I - f over the usable measurements
    and P = df/dA. The scratch rows of :func:`_view_terms` must be set."""
    j0 = chunk * CHUNK
    for i in range(N_SUMS * CHUNK):
        acc[i] = _F0
    value_floor = consts[VALUE_FLOOR]
    max_inv = _F1 / consts[DERIVATIVE_FLOOR]
    for k in range(meas.shape[1]):
        block = meas[chunk, k]
        for i in range(CHUNK):
            j = _U(j0 + i)
            nx, ny, nz = n[0, j], n[1, j], n[2, j]
            lx, ly, lz = block[LX, _U(i)], block[LY, _U(i)], block[LZ, _U(i)]
            ci = lx * nx + ly * ny + lz * nz
            # e p and e where lit (zero where not usable): a product, not a branch
            lit_f = _F1 if (ci > _F0) & (scr[_U(_SEEN + i)] > _F0) else _F0
            g = block[G, _U(i)] * lit_f
            em = block[E, _U(i)] * lit_f
            ci = _fmax(ci, value_floor)
            inv_ci = _F1 / ci
            q = ci / (ci + scr[_U(_CR + i)])
            big_e = _exp((inv_ci + scr[_U(_INV_CR + i)]) * neg_tau)
            p = (_F1 - big_e) * q * g  # e p S
            c = ci * em  # e c_i
            rho_j = rho[j]
            pa = p * a
            u = (_F1 - q) * pa
            r = block[VALUE, _U(i)] - pa - c * rho_j  # (I is 0 where not usable)
            wq = g * q * big_e * a_tau
            d_inv_cr = scr[_U(_DINV_CR + i)]
            d_inv_ci = _fmin(inv_ci, max_inv)
            dfr = (wq * d_inv_cr + u) * d_inv_cr  # -df/dc_r
            dfi = (u - wq * d_inv_ci) * d_inv_ci + em * rho_j  # df/dc_i
            j1 = (lx - ci * nx) * dfi - dfr * scr[_U(_VTX + i)]
            j2 = (ly - ci * ny) * dfi - dfr * scr[_U(_VTY + i)]
            acc[_U(_ACC[0] + i)] += j1 * j1
            acc[_U(_ACC[1] + i)] += j1 * j2
            acc[_U(_ACC[2] + i)] += j1 * c
            acc[_U(_ACC[3] + i)] += j2 * j2
            acc[_U(_ACC[4] + i)] += j2 * c
            acc[_U(_ACC[5] + i)] += c * c
            acc[_U(_ACC[6] + i)] += j1 * r
            acc[_U(_ACC[7] + i)] += j2 * r
            acc[_U(_ACC[8] + i)] += c * r
            acc[_U(_ACC[9] + i)] += j1 * p
            acc[_U(_ACC[10] + i)] += j2 * p
            acc[_U(_ACC[11] + i)] += c * p
            acc[_U(_ACC[12] + i)] += p * p
            acc[_U(_ACC[13] + i)] += p * r
            acc[_U(_ACC[14] + i)] += r * r
    for row in range(N_SUMS):
        off = row * CHUNK
        for i in range(CHUNK):
            sums[row, _U(j0 + i)] = acc[_U(off + i)]


@serial_kernel
def _steps(j0, sums, lam, consts, delta0, w):
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
        d1 = h11 + lj * _fmax(h11, tiny)
        d2 = h22 + lj * _fmax(h22, tiny)
        d3 = h33 + lj * _fmax(h33, tiny)
        a11, a12, a13, a22, a23, a33, det = _adjugate(d1, h12, h13, d2, h23, d3)
        ok = det > _SINGULAR * d1 * d2 * d3
        inv = _F1 / det
        inv_det = inv if ok else _F0
        raised = _fmin(lj * up, top)
        lam[j] = lj if ok else raised  # (nearly) singular: no step, more damping next time
        g1, g2, g3 = sums[6, j], sums[7, j], sums[8, j]
        c1, c2, c3 = sums[9, j], sums[10, j], sums[11, j]
        delta0[0, j], delta0[1, j], delta0[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, g1, g2, g3)
        w[0, j], w[1, j], w[2, j] = _adjugate_solve(
            a11, a12, a13, a22, a23, a33, inv_det, c1, c2, c3)


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


@serial_kernel
def _linear_rows(n, meas, chunk, neg_tau, consts, scr, rows):
    """For A's and rho's joint linear fit at the normals ``n``: per pixel of the chunk P.P,
    P.C, C.C, P.I, C.I (P = e p S, C = e c_i over the lit usable measurements) into its
    columns of ``rows`` (5, Np) float32. The scratch rows of :func:`_view_terms` must be
    set."""
    j0 = chunk * CHUNK
    value_floor = consts[VALUE_FLOOR]
    acc = np.zeros(5 * CHUNK, np.float32)
    for k in range(meas.shape[1]):
        block = meas[chunk, k]
        for i in range(CHUNK):
            j = _U(j0 + i)
            # as in _model_sums
            ci = (block[LX, _U(i)] * n[0, j] + block[LY, _U(i)] * n[1, j]
                  + block[LZ, _U(i)] * n[2, j])
            lit_f = _F1 if (ci > _F0) & (scr[_U(_SEEN + i)] > _F0) else _F0
            g = block[G, _U(i)] * lit_f
            em = block[E, _U(i)] * lit_f
            ci = _fmax(ci, value_floor)
            q = ci / (ci + scr[_U(_CR + i)])
            p = (_F1 - _exp((_F1 / ci + scr[_U(_INV_CR + i)]) * neg_tau)) * q * g
            c = ci * em
            val = block[VALUE, _U(i)]
            acc[_U(_ACC[0] + i)] += p * p
            acc[_U(_ACC[1] + i)] += p * c
            acc[_U(_ACC[2] + i)] += c * c
            acc[_U(_ACC[3] + i)] += p * val
            acc[_U(_ACC[4] + i)] += c * val
    for row in range(5):
        off = row * CHUNK
        for i in range(CHUNK):
            rows[row, _U(j0 + i)] = acc[_U(off + i)]


@parallel_kernel
def linear_sums(n, meas, views, neg_tau, consts, rows, parts):
    """The per-pixel sums of A's and rho's joint linear fit (:func:`_linear_rows`) into
    ``rows``, and per chunk the parts of the fit's numerator sum (P.I - P.C C.I / C.C) and
    denominator sum (P.P - (P.C)^2 / C.C) into ``parts`` (chunks, 2) float64."""
    for chunk in prange(parts.shape[0]):
        j0 = chunk * CHUNK
        scr = np.empty(_SCRATCH, np.float32)
        _view_terms(n, views, j0, consts, scr)
        _linear_rows(n, meas, chunk, neg_tau, consts, scr, rows)
        num = den = 0.0
        for i in range(CHUNK):
            j = _U(j0 + i)
            pp, pc = float(rows[0, j]), float(rows[1, j])
            cc = _fmax(float(rows[2, j]), 1e-30)
            num += float(rows[3, j]) - pc * float(rows[4, j]) / cc
            den += pp - pc * pc / cc
        parts[chunk, 0] = num
        parts[chunk, 1] = den


@serial_kernel
def _fit_rho(j0, rows, scale, rho):
    """rho of the chunk's pixels at ``j0`` in closed form for A = ``scale`` (float64) from
    the linear fit's per-pixel sums ``rows`` (:func:`_linear_rows`): (C.I - A P.C) / C.C,
    >= 0; kept where C.C = 0."""
    for i in range(CHUNK):
        j = _U(j0 + i)
        pc, cc, c_i = float(rows[1, j]), float(rows[2, j]), float(rows[4, j])
        fitted = _fmax((c_i - scale * pc) / _fmax(cc, 1e-30), 0.0)
        kept = float(rho[j])
        rho[j] = fitted if cc > 0.0 else kept


@serial_kernel
def _trial_state(j0, n, rho, delta0, w, d32, n_new, rho_new):
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
        rho_new[j] = _fmax(rho[j] + sr, _F0)


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
        scr = np.empty(_SCRATCH, np.float32)
        _view_terms(n, views, j0, consts, scr)
        if not rows_given:
            _linear_rows(n, meas, chunk, neg_tau, consts, scr, rows)
        _fit_rho(j0, rows, scale, rho)
        _model_sums(n, rho, chunk, a, a_tau, neg_tau, meas, consts, scr,
                    np.empty(N_SUMS * CHUNK, np.float32), sums)
        _steps(j0, sums, lam, consts, delta0, w)
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
        scr = np.empty(_SCRATCH, np.float32)
        _trial_state(j0, n, rho, delta0, w, d32, n_new, rho_new)
        _view_terms(n_new, views, j0, consts, scr)
        _model_sums(n_new, rho_new, chunk, a, a_tau, neg_tau, meas, consts, scr,
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


@serial_kernel
def _keep_better(j0, d_old, d_new, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
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
        scr[_U(_TAKE + i)] = _F1 if accept else _F0
        chosen[i] = new if accept else old
    for row in range(N_SUMS):  # J^T J, J^T P, P.P of the kept state (the rest below)
        if 6 <= row <= 8 or row >= 13:
            continue
        for i in range(CHUNK):
            j = _U(j0 + i)
            cand, kept = sums_new[row, j], sums[row, j]
            sums[row, j] = cand if scr[_U(_TAKE + i)] > _F0 else kept
    for i in range(CHUNK):
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
    for i in range(CHUNK):
        j = _U(j0 + i)
        accept = scr[_U(_TAKE + i)] > _F0
        nx, ny, nz, rho_j = n_new[0, j], n_new[1, j], n_new[2, j], rho_new[j]
        ox, oy, oz, rho_o = n[0, j], n[1, j], n[2, j], rho[j]
        n[0, j] = nx if accept else ox
        n[1, j] = ny if accept else oy
        n[2, j] = nz if accept else oz
        rho[j] = rho_j if accept else rho_o
        lj = lam[j] * (down if accept else up)
        lam[j] = _fmin(_fmax(lj, low), top)


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
        scr = np.empty(_SCRATCH, np.float32)
        chosen = np.empty(CHUNK)  # the chosen states' costs at A = at, float64
        _keep_better(j0, d_old, d_new, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
                     scr, chosen)
        _steps(j0, sums, lam, consts, delta0, w)
        _step_parts(j0, sums, delta0, w, parts, chunk)
        cost = 0.0
        for i in range(CHUNK):
            cost += chosen[i]
        parts[chunk, 0] = cost


@parallel_kernel
def finish(pix, solved, n, rho, sums, counts, normals, albedo, rms, valid):
    """The result images (flat (H*W,), zeros where not valid) from the state of every chunk
    (:func:`_finish_chunk`)."""
    for chunk in prange((pix.shape[0] + CHUNK - 1) // CHUNK):
        j0 = chunk * CHUNK
        _finish_chunk(pix, solved, j0, n, rho, sums, j0, counts, normals, albedo, rms, valid)


@serial_kernel
def _finish_chunk(pix, solved, j0, n, rho, sums, d0, counts, normals, albedo, rms, valid):
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
            rms[p] = math.sqrt(_fmax(float(sums[14, d]), 0.0) / counts[j])
            valid[p] = True


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
    pixels do not depend on each other, so each chunk is gathered (:func:`_gather_chunk`,
    arguments as :func:`gather`), solved and written out (:func:`_finish_chunk`) while its
    measurements and state stay in the core's cache -- one pass over the burst instead of
    two per iteration. The same steps as the passes with A fixed: rho in closed form at
    the initial normals, then up to ``iterations`` Levenberg–Marquardt iterations (damping
    from ``lam_start``), each pixel keeping the better of its state and its candidate; a
    chunk stops once the decrease its next steps promise (:func:`_predicted_decrease`) is
    at most ``tol`` times its cost, without evaluating them. Per chunk
    into ``parts`` (chunks, 5) float64: the initial and the final cost, the iterations
    done, and the numerator and denominator of A's linear fit (with every rho) at the
    final normals, sum (P.I - P.C C.I / C.C) and sum (P.P - (P.C)^2 / C.C), for the A the
    next burst is held at; ``flags`` (chunks,) as :func:`gather`."""
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
        scr = np.empty(_SCRATCH, f32)
        acc = np.empty(N_SUMS * CHUNK, f32)
        chosen = np.empty(CHUNK)
        flags[chunk] = _gather_chunk(chunk, cand, index, images, usable, normals_in,
                                     albedo_in, terms, views, bad, min_cr, meas[0], v, n, rho,
                                     0, solved, counts)
        _view_terms(n, v, 0, consts, scr)
        _linear_rows(n, meas, 0, neg_tau, consts, scr, rows)
        _fit_rho(0, rows, scale, rho)
        _model_sums(n, rho, 0, a, a_tau, neg_tau, meas, consts, scr, acc, sums)
        _steps(0, sums, lam, consts, delta0, w)
        cost = 0.0
        for i in range(CHUNK):
            cost += float(sums[14, i])
        parts[chunk, 0] = cost
        done = 0
        while done < iterations and _predicted_decrease(sums, delta0) > tol * cost:
            done += 1
            _trial_state(0, n, rho, delta0, w, f32(0.0), n_new, rho_new)
            _view_terms(n_new, v, 0, consts, scr)
            _model_sums(n_new, rho_new, 0, a, a_tau, neg_tau, meas, consts, scr, acc,
                        sums_new)
            _keep_better(0, 0.0, 0.0, consts, sums, sums_new, n, n_new, rho, rho_new, lam,
                         scr, chosen)
            _steps(0, sums, lam, consts, delta0, w)
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
        _finish_chunk(cand, solved, chunk * CHUNK, n, rho, sums, 0, counts, normals, albedo,
                      rms, valid)


# After an edit of a module whose functions the kernels inline (symmetric_solve), the
# cached kernels are compiled anew.
drop_stale_caches(globals())
