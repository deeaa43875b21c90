"""Compiled (numba) per-pixel step of the ridge enhancement (paper Eq. 12,
:mod:`photometric.normal_transform`).

After the patch sums s = sum_{j in w x w} n_j (OpenCV's box filter), every pixel's
n' = (1 + k) n - k s / |s|, renormalised, is one pass over the planes in a loop without
branches (selects), which LLVM vectorises, instead of some twenty numpy passes. Importing
this module needs numba; the compiled code is cached on disk as the other kernels'
(:mod:`photometric.kernel_compile`).
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import drop_stale_caches, serial_kernel


@serial_kernel
def enhance_planes(x, y, z, sx, sy, sz, gain, one_k):
    """In place: the unit normal planes x, y, z (h, w) become the enhanced ones.

    Parameters
    ----------
    x, y, z : (h, w) float32 or float64, C-contiguous
        Normals; zero vectors mark pixels without a normal (zero out).
    sx, sy, sz : (h, w), the same dtype
        Their w x w patch sums.
    gain, one_k : scalars of that dtype
        k and 1 + k.
    """
    zero = gain - gain
    one = one_k - gain
    h, w = x.shape
    for r in range(h):
        for c in range(w):
            nx, ny, nz = x[r, c], y[r, c], z[r, c]
            has = (nx != zero) | (ny != zero) | (nz != zero)
            ax, ay, az = sx[r, c], sy[r, c], sz[r, c]
            s_norm = np.sqrt(ax * ax + ay * ay + az * az)
            # where no neighbour has a normal (s = 0) the mean direction is n itself
            inv_s = gain / s_norm if s_norm > zero else zero
            ex = one_k * nx - inv_s * ax
            ey = one_k * ny - inv_s * ay
            ez = one_k * nz - inv_s * az
            e_norm = np.sqrt(ex * ex + ey * ey + ez * ez)
            inv_e = one / e_norm if has & (e_norm > zero) else zero
            x[r, c] = ex * inv_e
            y[r, c] = ey * inv_e
            z[r, c] = ez * inv_e


# After an edit of the compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
