"""The inputs of the HK solver's compiled (numba) passes (paper Eq. 4, 6-7): the lighting
of a calibration per pixel and light (:func:`lighting_terms`: the unit light direction, the
light's relative intensity e_k, and e_k times the phase function p(c, g) of Eq. 4; near
lights at the points of a depth map: :func:`near_lighting_terms`), and a
burst's pixels gathered into the passes' layout (:func:`gather`, chunk by chunk
:func:`gather_chunk`), both as :mod:`photometric.hk_model_kernel` describes them."""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from fingerps_recon.photometric.hk_model_kernel import (
    BAD_LIGHT,
    BAD_VIEW,
    CHUNK,
    LX,
    LY,
    LZ,
    N_TERMS,
    VALUE,
    ZERO_LIGHT,
    ZERO_VIEW,
    E,
    G,
    fmax,
    fmin,
)
from fingerps_recon.photometric.kernel_compile import (
    drop_stale_caches,
    parallel_kernel,
    serial_kernel,
)

# Unsigned indices: numba then needs no wrap-around of negative ones, and LLVM vectorises.
_U = numba.uint64
# Blocks of chunks near_lighting_terms' threads take (each block's scratch allocated once).
_BLOCKS = 32


@parallel_kernel
def lighting_terms(pixels, lights, views, intensity, hg, physical, terms, v_out, bad):
    """The lighting of the image pixels ``pixels`` (Q,) (the layout of
    :mod:`photometric.hk_model_kernel`): ``terms`` (K, N_TERMS, Q) float32, ``v_out`` (3, Q)
    float32 and ``bad`` (Q,) uint8. ``lights``
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
                c_sc = fmin(fmax(c_sc, -one), one)
                denom = hg_a - hg_b * c_sc
                phase = hg_num / (four_pi * denom * np.sqrt(denom))
                terms[k, LX, q], terms[k, LY, q], terms[k, LZ, q] = lx, ly, lz
                terms[k, G, q] = e * phase if usable else zero
                terms[k, E, q] = e if usable else zero
            bad[q] = np.uint8(flag)


@parallel_kernel
def near_lighting_terms(pixels, depth, leds, plane_power, working, views, view_index, hg,
                        physical, terms, v_out, bad):
    """:func:`lighting_terms` of near point lights at the surface points of a depth map: for
    the image pixels ``pixels`` (Q,), the point P = z r on the pixel's ray r at the depth
    z = ``depth`` (H*W,) float32 (the plane z = ``working`` where it is not finite or
    <= 0), the unit direction from P towards each LED ``leds`` (K, 3) (optical frame,
    written in the PS frame) and its irradiance, ``plane_power`` (K, H*W) or (K, 1)
    float32 (the irradiance on the plane z = ``working``) moved from the plane's point to P
    by the inverse-square law (the LED's emission lobe taken as constant over the move).
    The view of pixel p is column ``view_index[p]`` of ``views`` (3, .) float32 (a
    perspective lighting's ``v_out``: the unit vector towards the camera, minus the ray, in
    the PS frame), and so is its ray: r = (-v_x, v_y, v_z) / v_z (optical frame, z = 1).
    The other arguments and the outputs as :func:`lighting_terms`. float32 arithmetic, the
    lights' loops over a chunk's pixels (vectorised)."""
    count = pixels.shape[0]
    k_count = terms.shape[0]
    hg_a, hg_b, hg_num, four_pi = hg[0], hg[1], hg[2], hg[3]
    per_pixel_power = plane_power.shape[1] > 1
    sign = np.float32(-1.0) if physical else np.float32(1.0)
    one, zero = np.float32(1.0), np.float32(0.0)
    f32 = np.float32
    wd = f32(working)
    chunks = (count + CHUNK - 1) // CHUNK
    blocks = min(chunks, _BLOCKS)
    for block in prange(blocks):
        # A block's scratch (allocated once: allocations in a parallel loop are costly),
        # then its chunks, every ``blocks``-th: the chunk's points and the plane's, and
        # views; then per light, loops that each write one array, with unsigned indices, so
        # that LLVM vectorises them (as gather_chunk's).
        ptx = np.empty(CHUNK, np.float32)
        pty = np.empty(CHUNK, np.float32)
        ptz = np.empty(CHUNK, np.float32)
        plx = np.empty(CHUNK, np.float32)
        ply = np.empty(CHUNK, np.float32)
        plz = np.empty(CHUNK, np.float32)
        vx = np.empty(CHUNK, np.float32)
        vy = np.empty(CHUNK, np.float32)
        vz = np.empty(CHUNK, np.float32)
        power_at = np.empty(CHUNK, np.int64)
        inv = np.empty(CHUNK, np.float32)
        ratio = np.empty(CHUNK, np.float32)
        power = np.empty(CHUNK, np.float32)
        cos = np.empty(CHUNK, np.float32)
        flags = np.empty(CHUNK, np.uint8)
        for chunk in range(block, chunks, blocks):
            q0 = chunk * CHUNK
            m = _U(min(q0 + CHUNK, count) - q0)
            for i in range(m):  # gathers
                p = pixels[q0 + i]
                pv = view_index[p]
                vx[i], vy[i], vz[i] = views[0, pv], views[1, pv], views[2, pv]
                z = depth[p]
                inv[i] = f32(z) if (math.isfinite(z) and z > 0.0) else wd  # (the depth here)
                power_at[i] = p if per_pixel_power else 0
            for i in range(m):
                a, b, c = vx[i], vy[i], vz[i]
                v_out[0, q0 + i], v_out[1, q0 + i], v_out[2, q0 + i] = a, b, c
                norm = np.sqrt(a * a + b * b + c * c)
                flag = 0 if norm - norm == 0 else BAD_VIEW  # (not inf, not nan)
                flags[i] = flag if (norm != 0) & (c > zero) else ZERO_VIEW
            for i in range(m):  # the ray (z = 1), the plane's point and the surface's
                c = vz[_U(i)]
                c = c if c > zero else one
                x, y = -vx[_U(i)] / c, vy[_U(i)] / c
                z = inv[_U(i)]
                plx[_U(i)], ply[_U(i)], plz[_U(i)] = wd * x, wd * y, wd
                ptx[_U(i)], pty[_U(i)], ptz[_U(i)] = z * x, z * y, z
            for k in range(k_count):
                lx0, ly0, lz0 = f32(leds[k, 0]), f32(leds[k, 1]), f32(leds[k, 2])
                out_x, out_y, out_z = terms[k, LX, q0:], terms[k, LY, q0:], terms[k, LZ, q0:]
                out_g, out_e = terms[k, G, q0:], terms[k, E, q0:]
                source = plane_power[k]
                for i in range(m):
                    power[_U(i)] = source[power_at[_U(i)]]
                for i in range(m):
                    dx = lx0 - ptx[_U(i)]
                    dy = ly0 - pty[_U(i)]
                    dz = lz0 - ptz[_U(i)]
                    inv[_U(i)] = one / np.sqrt(dx * dx + dy * dy + dz * dz)
                for i in range(m):  # (plane distance / distance)^2
                    dx = lx0 - plx[_U(i)]
                    dy = ly0 - ply[_U(i)]
                    dz = lz0 - plz[_U(i)]
                    r = inv[_U(i)]
                    ratio[_U(i)] = (dx * dx + dy * dy + dz * dz) * (r * r)
                # optical -> PS frame (x, -y, -z)
                for i in range(m):
                    out_x[_U(i)] = (lx0 - ptx[_U(i)]) * inv[_U(i)]
                for i in range(m):
                    out_y[_U(i)] = (pty[_U(i)] - ly0) * inv[_U(i)]
                for i in range(m):
                    out_z[_U(i)] = (ptz[_U(i)] - lz0) * inv[_U(i)]
                for i in range(m):
                    power[_U(i)] = power[_U(i)] * ratio[_U(i)]
                for i in range(m):
                    e = power[_U(i)]
                    out_e[_U(i)] = e if (e - e == zero) & (e > zero) else zero
                for i in range(m):
                    c_sc = sign * (out_x[_U(i)] * vx[_U(i)] + out_y[_U(i)] * vy[_U(i)]
                                   + out_z[_U(i)] * vz[_U(i)])
                    cos[_U(i)] = fmin(fmax(c_sc, -one), one)
                for i in range(m):
                    denom = hg_a - hg_b * cos[_U(i)]
                    out_g[_U(i)] = out_e[_U(i)] * (hg_num / (four_pi * denom * np.sqrt(denom)))
                if not (lx0 - lx0 == zero and ly0 - ly0 == zero and lz0 - lz0 == zero):
                    for i in range(m):
                        flags[i] |= BAD_LIGHT
            for i in range(m):
                bad[q0 + i] = flags[i]


@parallel_kernel
def gather(cand, index, images, usable, normals, albedo, terms, views, bad, min_cr, meas,
           v_dirs, n0, rho0, solved, counts, flags):
    """The mask's pixels ``cand`` (N,) (increasing image indices) in the passes' layout,
    padded to ``chunks * CHUNK`` (the layout of :mod:`photometric.hk_model_kernel`):
    ``meas`` (chunks, K, N_MEAS, CHUNK) float32, ``v_dirs`` (3, Np), ``n0`` (3, Np),
    ``rho0`` (Np,), ``counts``, ``solved`` and ``flags`` (chunks,) uint8 as
    :func:`gather_chunk` fills them, chunk by chunk."""
    for chunk in prange(meas.shape[0]):
        flags[chunk] = gather_chunk(chunk, cand, index, images, usable, normals, albedo,
                                    terms, views, bad, min_cr, meas[chunk], v_dirs, n0,
                                    rho0, chunk * CHUNK, solved, counts)


@serial_kernel
def gather_chunk(chunk, cand, index, images, usable, normals, albedo, terms, views, bad,
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


# After an edit of a module whose functions the kernels here compile, or of the
# compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
