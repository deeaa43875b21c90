"""Compiled (numba) per-pixel loop of the Lambertian solver (:mod:`photometric.lambertian`).

Paper Eq. 3 (NOTES §2): per pixel, I_k = e_k rho (l_k . n) over the lights k usable there;
with a_k = e_k l_k, the 3x3 normal equations A b = r, A = sum_k a_k a_k^T, r = sum_k a_k I_k,
give b = rho n = A^-1 r, solved in closed form by the adjugate of the symmetric A
(:mod:`photometric.symmetric_solve`).

One kernel, :func:`solve`, for distant lights (one row a_k per light) and near lights (one
per light and pixel): the rows a_k = e_k l_k come made, once per calibration, as planes
(K, 3, H, W) or constants (K, 3, 1, 1) (:func:`photometric.lambertian.light_rows`), NaN
where light k is not usable at a pixel. The image rectangle is cut into chunks of at most
``CHUNK`` pixels of one row (each chunk narrowed to its first and last mask pixel, empty ones
skipped, its loops' window widened to a multiple of 16 pixels so that no scalar remainder
loop is left), dealt out to numba's threads (``prange``). Per chunk, light by light, the nine
sums of A and r are accumulated in float32 for every pixel of the chunk in a loop over
consecutive pixels without branches (selects) that reads the image row and the three row
planes where they are (no copy into a scratch), which LLVM vectorises (8 pixels at a time
with AVX2, 16 with AVX-512); the images are read as they are (uint8, uint16, float32,
float64: no float copy of the burst). Then, per pixel, the adjugate solve, the degenerate
test, rho = |b|, n = b / rho, and the results are written into the caller's images. Last,
the chunk's images and rows are read once more (from the cache) for the Lambertian misfit
of the solved pixels, sum_k (I_k - max(0, b . a_k))^2 (= (I_k - e_k rho max(0, n . l_k))^2)
over their used lights, and the sum and number of those I_k, per chunk in float64. The cost
per pixel and light does not grow with the number of lights K: nothing is sized by K but
the inputs, and a chunk's sums and scratch stay in the core's L1 cache.

A light k is used at a pixel if the pixel is in the mask, its value I_k is > ``lo`` (not
shadowed) and < ``hi`` (not saturated; NaN fails both) and its row a_k is finite. A pixel is
solved if it uses at least 3 lights and its A is not degenerate: det(A) > ``min_det``
(trace(A) / 3)^3 (its light directions not coplanar).

Importing this module needs numba. The compiled code is cached on disk (``cache=True``:
numba's ``__pycache__`` beside this file when writable, else the user's cache directory, or
``NUMBA_CACHE_DIR``); where no cache directory is writable the kernel is compiled in every
process (a warning says so). Each combination of input dtypes is compiled once on first use.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    inline_kernel,
    parallel_kernel,
)
from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

# Pixels per chunk (a chunk's nine float32 sums, its scratch and its pixels' inputs stay in
# the core's L1/L2 cache, whatever the number of lights).
CHUNK = 256
# Pixels the per-pixel loops run over come in multiples of this (two AVX2 vectors of float32,
# one AVX-512 one): the loops have no scalar remainder. CHUNK is a multiple of it.
_LANES = 16

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64
# Rows of a chunk's float32 scratch: the mask (1 or 0), the solution b = rho n, whether it
# is valid (1 or 0), n and rho.
(_IN, _BX, _BY, _BZ, _OK, _NX, _NY, _NZ, _RHO) = (row * CHUNK for row in range(9))
_SCRATCH = 9 * CHUNK
# Rows of a chunk's sums: A (upper triangle), r, the count of used lights.
(_AXX, _AXY, _AXZ, _AYY, _AYZ, _AZZ, _RX, _RY, _RZ, _CNT) = (row * CHUNK for row in range(10))
_SUMS = 10 * CHUNK

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_THIRD = np.float32(1.0 / 3.0)
_INF = np.float32(np.inf)

# The symmetric 3x3 solve by the adjugate (photometric.symmetric_solve), inlined.
_adjugate = inline_kernel(symmetric_adjugate)
_adjugate_solve = inline_kernel(adjugate_solve)


@inline_kernel
def _used(v, lo, hi, inside, ax, ay, az):
    """Whether a measurement is used (see the module docstring); NaN fails every test."""
    finite = (ax - ax == _F0) & (ay - ay == _F0) & (az - az == _F0)
    return (inside > _F0) & (v > lo) & (v < hi) & finite


@inline_kernel
def _add(v, ax, ay, az, inside, lo, hi, acc, i):
    """One measurement I_k = v with row a_k = (ax, ay, az) into pixel i's sums, if used."""
    use = _used(v, lo, hi, inside, ax, ay, az)
    ax = ax if use else _F0
    ay = ay if use else _F0
    az = az if use else _F0
    value = np.float32(v) if use else _F0
    acc[_U(_AXX + i)] += ax * ax
    acc[_U(_AXY + i)] += ax * ay
    acc[_U(_AXZ + i)] += ax * az
    acc[_U(_AYY + i)] += ay * ay
    acc[_U(_AYZ + i)] += ay * az
    acc[_U(_AZZ + i)] += az * az
    acc[_U(_RX + i)] += ax * value
    acc[_U(_RY + i)] += ay * value
    acc[_U(_RZ + i)] += az * value
    acc[_U(_CNT + i)] += _F1 if use else _F0


@inline_kernel
def _add_misfit(v, ax, ay, az, ok, bx, by, bz, lo, hi, acc, i):
    """One measurement's misfit (I_k - max(0, b . a_k))^2, I_k and 1 into pixel i's sums
    (rows _AXX, _AXY, _AXZ), if used at a solved pixel."""
    use = _used(v, lo, hi, ok, ax, ay, az)
    shade = bx * ax + by * ay + bz * az
    value = np.float32(v) if use else _F0
    predicted = (shade if shade > _F0 else _F0) if use else _F0
    diff = value - predicted
    acc[_U(_AXX + i)] += diff * diff
    acc[_U(_AXY + i)] += value
    acc[_U(_AXZ + i)] += _F1 if use else _F0


@inline_kernel
def _span(chunk, r0, c0, c1, mask):
    """(row, first column, number of pixels) of ``chunk``, narrowed to its first and last
    mask pixel."""
    per_row = (c1 - c0 + CHUNK - 1) // CHUNK
    r = r0 + chunk // per_row
    start = c0 + (chunk % per_row) * CHUNK
    stop = min(start + CHUNK, c1)
    while start < stop and not mask[r, start]:
        start += 1
    while stop > start and not mask[r, stop - 1]:
        stop -= 1
    return r, start, stop - start


@inline_kernel
def _measure(v, ax, ay, az, scr, lo, hi, acc, i, misfit):
    """One measurement I_k = v with row a_k = (ax, ay, az) of pixel i: into its normal
    equations (``misfit`` False: inside-the-span row _IN of ``scr``) or its misfit (True:
    the solution rows _BX ... _OK)."""
    if misfit:
        _add_misfit(v, ax, ay, az, scr[_U(_OK + i)], scr[_U(_BX + i)], scr[_U(_BY + i)],
                    scr[_U(_BZ + i)], lo, hi, acc, i)
    else:
        _add(v, ax, ay, az, scr[_U(_IN + i)], lo, hi, acc, i)


@inline_kernel
def _over_lights(images, rows, r, start, m, lo, hi, scr, acc, misfit):
    """Every light's measurements of the window's pixels (columns start ... start + m - 1
    of row r) into ``acc`` by :func:`_measure`, light by light, with the rows a_k read per
    pixel (near lights) or once per light (distant ones). ``misfit`` is a constant at each
    call, so that each call's loop is compiled for its one kind of sum."""
    for k in range(images.shape[0]):
        image = images[k, r]
        if rows.shape[2] > 1 or rows.shape[3] > 1:
            row_x, row_y, row_z = rows[k, 0, r], rows[k, 1, r], rows[k, 2, r]
            for i in range(m):
                c = _U(start + i)
                _measure(image[c], row_x[c], row_y[c], row_z[c], scr, lo, hi, acc, i, misfit)
        else:
            ax, ay, az = rows[k, 0, 0, 0], rows[k, 1, 0, 0], rows[k, 2, 0, 0]
            for i in range(m):
                _measure(image[_U(start + i)], ax, ay, az, scr, lo, hi, acc, i, misfit)


@inline_kernel
def _accumulate(images, rows, mask, r, start, m, offset, span, lo, hi, scr, acc):
    """The chunk's normal equations: per pixel of the window (columns start ... start +
    m - 1), A (upper triangle), r = sum a_k I_k and the count of used lights into ``acc``
    (zero on entry), light by light; only the mask pixels of the chunk's own span (window
    pixels offset ... offset + span - 1) count as inside."""
    for i in range(m):
        own = (i >= offset) & (i < offset + span)
        scr[_U(_IN + i)] = _F1 if own and mask[r, _U(start + i)] else _F0
    _over_lights(images, rows, r, start, m, lo, hi, scr, acc, False)


@inline_kernel
def _solve_pixels(r, start, m, offset, span, min_det, acc, scr, normals, albedo, valid, used):
    """Per pixel of the chunk: b = A^-1 r by the adjugate, the degenerate test, rho = |b|,
    n = b / rho into the scratch rows _BX ... _RHO (vectorised), then into the result
    images."""
    for i in range(m):
        a_xx, a_xy, a_xz = acc[_U(_AXX + i)], acc[_U(_AXY + i)], acc[_U(_AXZ + i)]
        a_yy, a_yz, a_zz = acc[_U(_AYY + i)], acc[_U(_AYZ + i)], acc[_U(_AZZ + i)]
        r_x, r_y, r_z = acc[_U(_RX + i)], acc[_U(_RY + i)], acc[_U(_RZ + i)]
        # A^-1 = adj(A) / det(A)
        c_xx, c_xy, c_xz, c_yy, c_yz, c_zz, det = _adjugate(a_xx, a_xy, a_xz, a_yy, a_yz, a_zz)
        trace = (a_xx + a_yy + a_zz) * _THIRD
        solved = (acc[_U(_CNT + i)] >= np.float32(3.0)) & (
            det > min_det * trace * trace * trace)
        inv_det = _F1 / det if solved else _F0
        bx, by, bz = _adjugate_solve(c_xx, c_xy, c_xz, c_yy, c_yz, c_zz, inv_det, r_x, r_y,
                                     r_z)
        rho = np.sqrt(bx * bx + by * by + bz * bz)
        ok = solved & (rho > _F0) & (rho < _INF)
        inv_rho = _F1 / rho if ok else _F0
        scr[_U(_BX + i)] = bx if ok else _F0
        scr[_U(_BY + i)] = by if ok else _F0
        scr[_U(_BZ + i)] = bz if ok else _F0
        scr[_U(_OK + i)] = _F1 if ok else _F0
        scr[_U(_NX + i)] = bx * inv_rho if ok else _F0
        scr[_U(_NY + i)] = by * inv_rho if ok else _F0
        scr[_U(_NZ + i)] = bz * inv_rho if ok else _F0
        scr[_U(_RHO + i)] = rho if ok else _F0
    for i in range(offset, offset + span):  # the span's pixels only
        c = _U(start + i)
        normals[r, c, 0] = scr[_U(_NX + i)]
        normals[r, c, 1] = scr[_U(_NY + i)]
        normals[r, c, 2] = scr[_U(_NZ + i)]
        albedo[r, c] = scr[_U(_RHO + i)]
        valid[r, c] = scr[_U(_OK + i)] > _F0
        used[r, c] = np.int32(acc[_U(_CNT + i)])


@inline_kernel
def _misfit(images, rows, r, start, m, lo, hi, scr, acc, parts, chunk):
    """The chunk's misfit at its solved pixels (scratch rows _BX ... _OK): sum of
    (I_k - max(0, b . a_k))^2, of I_k and their number over the used measurements into
    ``parts[chunk]`` (float64); ``acc``'s first three rows are overwritten."""
    for i in range(m):
        acc[_U(_AXX + i)] = _F0
        acc[_U(_AXY + i)] = _F0
        acc[_U(_AXZ + i)] = _F0
    _over_lights(images, rows, r, start, m, lo, hi, scr, acc, True)
    sq = total = count = 0.0
    for i in range(m):
        sq += float(acc[_U(_AXX + i)])
        total += float(acc[_U(_AXY + i)])
        count += float(acc[_U(_AXZ + i)])
    parts[chunk, 0] = sq
    parts[chunk, 1] = total
    parts[chunk, 2] = count


@parallel_kernel
def solve(images, rows, mask, box, lo, hi, min_det, normals, albedo, valid, used, parts):
    """Solve every mask pixel of the rectangle ``box`` (see the module docstring).

    Parameters
    ----------
    images : (K, H, W) uint8, uint16, float32 or float64, C-contiguous
    rows : (K, 3, H, W) or (K, 3, 1, 1) float32, C-contiguous
        a_k = e_k l_k (x, y, z planes), per pixel or one per light; NaN where light k is
        not usable.
    mask : (H, W) bool
        The pixels to solve.
    box : (4,) int64
        The rectangle: rows box[0] ... box[1] - 1, columns box[2] ... box[3] - 1.
    lo, hi : float32 (uint8, uint16 or float32 images) or float64 (float64 images)
        Shadow and saturation levels, as :func:`photometric.lambertian._levels` makes them.
    min_det : float32
        Relative determinant below which A is degenerate.
    normals : (H, W, 3) float32, albedo : (H, W) float32, valid : (H, W) bool,
    used : (H, W) uint8 or uint16
        Outputs, zero on entry; written only in the rectangle's rows, from each chunk's first
        to its last mask pixel.
    parts : (chunks, 3) float64, chunks = its rows x ceil(its columns / CHUNK)
        Zero on entry; per chunk, over its solved pixels' used measurements:
        sum (I_k - max(0, b . a_k))^2, sum I_k and their number (the caller adds
        them up in order, so that the totals do not depend on the threads).
    """
    for chunk in prange(parts.shape[0]):
        r, first, span = _span(chunk, box[0], box[2], box[3], mask)
        if span == 0:
            continue
        # The loops run over a window of a multiple of _LANES pixels holding the span (no
        # scalar remainder loop), moved left where the image row ends.
        m = min((span + _LANES - 1) // _LANES * _LANES, mask.shape[1])
        start = min(first, mask.shape[1] - m)
        offset = first - start
        scr = np.empty(_SCRATCH, np.float32)
        acc = np.zeros(_SUMS, np.float32)
        _accumulate(images, rows, mask, r, start, m, offset, span, lo, hi, scr, acc)
        _solve_pixels(r, start, m, offset, span, min_det, acc, scr, normals, albedo, valid,
                      used)
        _misfit(images, rows, r, start, m, lo, hi, scr, acc, parts, chunk)


# After an edit of a module whose functions the kernels inline (symmetric_solve), the
# cached kernels are compiled anew.
drop_stale_caches(globals())
