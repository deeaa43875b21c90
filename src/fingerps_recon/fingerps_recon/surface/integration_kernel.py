"""Compiled (numba) per-pixel step of the perspective integration
(:func:`surface.integration.integrate_normals_perspective`): the log-depth steps.

From PS-frame normals (x, y, z interleaved, need not be unit) and the pixel rays, per pixel
of the box, in float32 (the module docstring of :mod:`surface.integration`):
D = max(nz - nx x_n + ny y_n, min_nz |n| |r|), du = nx / (fx D),
dv = -(ny + s nx / fx) / (fy D), both 0 where the pixel is outside the mask or its normal is
zero or not finite. One pass in a loop without branches (selects), which LLVM vectorises,
instead of some fifteen numpy passes. Importing this module needs numba; the compiled code
is cached on disk as the other kernels' (:mod:`photometric.kernel_compile`).
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import serial_kernel

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_INF = np.float32(np.inf)


@serial_kernel
def log_depth_steps(normals, mask, r0, c0, x_n, y_n, skew, min_nz, fx, fy, du, dv):
    """du, dv (h, w) float32 (written) for the box of h x w pixels from row r0, column c0
    of ``normals`` (H, W, 3) float32 and ``mask`` (H, W) bool (C-contiguous); ``x_n``
    (1, w) or, with a skew, (h, w) and ``y_n`` (h,) float32 the box's rays' normalised
    coordinates (x_n with the skew taken out), ``skew`` = s / fx, ``min_nz``, ``fx``,
    ``fy`` float32."""
    h, w = du.shape
    minus_ratio = -fx / fy
    for r in range(h):
        yn = y_n[r]
        xr = r if x_n.shape[0] > 1 else 0
        for c in range(w):
            nx = normals[r0 + r, c0 + c, 0]
            ny = normals[r0 + r, c0 + c, 1]
            nz = normals[r0 + r, c0 + c, 2]
            xn = x_n[xr, c]
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            usable = mask[r0 + r, c0 + c] & (norm > _F0) & (norm < _INF)
            ray = np.sqrt(xn * xn + yn * yn + _F1)
            den = nz - nx * xn + ny * yn
            low = min_nz * ray * norm
            den = den if den > low else low
            den = den * fx
            inv = _F1 / den if usable else _F0
            du[r, c] = nx * inv if usable else _F0
            dv[r, c] = (ny + skew * nx) * minus_ratio * inv if usable else _F0
