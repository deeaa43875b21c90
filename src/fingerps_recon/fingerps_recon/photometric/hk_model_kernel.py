"""The HK model of paper Eq. 4 compiled (numba) for the solver's passes (Eq. 6-7), and the data
layout those passes share.

Per chunk of ``CHUNK`` pixels the model of Eq. 4, its Jacobian and the 15 Gauss–Newton sums
of every pixel are formed light by light (:func:`model_sums`) while the chunk's sums stay in
the core's L1 cache, and nothing of size (K, N) is written; :func:`linear_rows` forms the
per-pixel sums of the fit that is linear in A and rho. The passes that call them:
:mod:`photometric.hk_passes_kernel` (A held, and A fitted jointly), with the steps of
:mod:`photometric.hk_step_kernel`.

Layout.

- The lighting, which depends on the calibration only
  (:func:`photometric.hk_gather_kernel.lighting_terms`, once per calibration and camera):
  per prepared pixel q and light k, ``terms`` (K, N_TERMS, Q)
  float32 rows ``LX, LY, LZ`` (the unit light direction), ``G`` (e_k p(c, g)) and ``E``
  (e_k; 0 where the intensity is not usable); ``views`` (3, Q) the unit view directions;
  ``bad`` (Q,) flags of non-finite or zero directions.
- A burst (:func:`photometric.hk_gather_kernel.gather`): the N pixels of its mask, padded to
  ``chunks * CHUNK`` (padding pixels and those that cannot be solved have no usable
  measurement, normal (0, 0, 1) and albedo 0: their sums are zero, they take no step and
  add nothing to the global sums),
  so that every loop over a chunk has the constant trip count ``CHUNK``. ``meas``
  (chunks, K, N_MEAS, CHUNK) float32: per chunk and light one contiguous block of the
  lighting rows and ``VALUE`` (I), with G, E and I zero where the measurement is not
  usable -- so that an unusable measurement adds exactly nothing to any sum, and a pass
  reads one sequential stream. Views (3, Np), the state component-major: normals
  (3, Np), sums (N_SUMS, Np) in the order of :func:`model_sums`. Scalars: ``a``
  (A), ``a_tau`` (A tau_d) and ``neg_tau`` (-tau_d) as float32; ``consts`` float32
  (indices below).

Vectorisation (LLVM, 8 float32 lanes with AVX2, 16 with AVX-512): the loops over a
chunk's pixels have no calls and no branches -- min/max are written as selects
(:func:`fmax`, :func:`fmin`: numba's builtin ``min``/``max`` on floats keep LLVM from
vectorising a loop), exp() is inlined arithmetic (:func:`_exp`, relative error < 4e-6)
whose power of two is a bit cast (:func:`_int_bits_as_float`) -- and unit strides.

The compiled code is cached on disk (``cache=True``: in the package's ``__pycache__``, else
the user's cache directory, or ``NUMBA_CACHE_DIR`` when set); where no cache directory is
writable the kernels are compiled in every process (a warning says so).
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.extending import intrinsic

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    serial_kernel,
)

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
_CR, _INV_CR, _DINV_CR, _VTX, _VTY, _SEEN, TAKE = (row * CHUNK for row in range(7))
SCRATCH = 7 * CHUNK
_ACC = tuple(row * CHUNK for row in range(N_SUMS))

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_HALF = np.float32(0.5)
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


@intrinsic
def _int_bits_as_float(typingctx, bits):
    """The float32 whose bits are the int32 ``bits`` (an LLVM bit cast, which vectorises;
    ``np.int32(bits).view(np.float32)`` does not)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return numba.float32(numba.int32), codegen


@inline_kernel
def fmax(a, b):
    """max(a, b) as a select (NaN in ``a`` propagates)."""
    return b if a < b else a


@inline_kernel
def fmin(a, b):
    """min(a, b) as a select (NaN in ``a`` propagates)."""
    return b if a > b else a


@inline_kernel
def _exp(x):
    """exp(x), float32, relative error < 4e-6 for -87.33 <= x <= 88 (branch-free, inlined).
    In the model it multiplies terms below 3e-4 of the single-scattering term for the
    finger's skin constants (``hk_solver``), so its error is below 1.2e-9 of that term."""
    x = fmax(x, _EXP_LO)
    fn = np.floor(x * _LOG2E + _HALF)
    r = x - fn * _LN2_HI
    r = r - fn * _LN2_LO
    poly = (((_P4 * r + _P3) * r + _P2) * r + _P1) * r + _P0
    return poly * _int_bits_as_float((np.int32(fn) + _BIAS) << _MANTISSA)  # poly 2^fn


@serial_kernel
def view_terms(n, views, j0, consts, scr):
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
        cr = fmax(cr, value_floor)
        scr[_U(_CR + i)] = cr
        scr[_U(_INV_CR + i)] = _F1 / cr
        scr[_U(_DINV_CR + i)] = _F1 / fmax(cr, derivative_floor)
        scr[_U(_VTX + i)] = vx - cr * nx
        scr[_U(_VTY + i)] = vy - cr * ny


@serial_kernel
def model_sums(n, rho, chunk, a, a_tau, neg_tau, meas, consts, scr, acc, sums):
    """The 15 Gauss–Newton sums of the chunk's pixels at normals ``n``, albedo ``rho`` and
    A = ``a`` into ``sums[:, chunk * CHUNK:][:, :CHUNK]``: J^T J (upper triangle, unknowns
    (a, b, rho)), J^T r, J^T P, P.P, P.r, r.r, with r = I - f over the usable measurements
    and P = df/dA. The scratch rows of :func:`view_terms` must be set."""
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
            ci = fmax(ci, value_floor)
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
            d_inv_ci = fmin(inv_ci, max_inv)
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
def linear_rows(n, meas, chunk, neg_tau, consts, scr, rows):
    """For A's and rho's joint linear fit at the normals ``n``: per pixel of the chunk P.P,
    P.C, C.C, P.I, C.I (P = e p S, C = e c_i over the lit usable measurements) into its
    columns of ``rows`` (5, Np) float32. The scratch rows of :func:`view_terms` must be
    set."""
    j0 = chunk * CHUNK
    value_floor = consts[VALUE_FLOOR]
    acc = np.zeros(5 * CHUNK, np.float32)
    for k in range(meas.shape[1]):
        block = meas[chunk, k]
        for i in range(CHUNK):
            j = _U(j0 + i)
            # as in model_sums
            ci = (block[LX, _U(i)] * n[0, j] + block[LY, _U(i)] * n[1, j]
                  + block[LZ, _U(i)] * n[2, j])
            lit_f = _F1 if (ci > _F0) & (scr[_U(_SEEN + i)] > _F0) else _F0
            g = block[G, _U(i)] * lit_f
            em = block[E, _U(i)] * lit_f
            ci = fmax(ci, value_floor)
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


# After an edit of a module whose functions the kernels here compile, or of the
# compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
