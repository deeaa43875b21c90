"""Compiled (numba) back-projection of a depth map to points
(:func:`surface.back_projection.depth_to_points`, which states the equations).

One pass in raster order over the mask's bounding box writes each kept pixel's point and
flat index: no planes of the box, no boolean gathers. Runs on the calling thread
(``serial_kernel``) and is cached on disk as the other kernels. Importing this module needs
numba.
"""

from __future__ import annotations

import numpy as np

from fingerps_recon.photometric.kernel_compile import drop_stale_caches, serial_kernel


@serial_kernel
def back_project(depth, mask, r0, c0, y_row, x_col, skew, points, index):
    """Write the points of the box rows r0 ... r0 + len(y_row) - 1, columns c0 ... c0 +
    len(x_col) - 1 whose pixel is in ``mask`` with a depth z > 0 and finite, in raster
    order; return how many.

    Parameters
    ----------
    depth : (H, W) float32, C-contiguous
    mask : (H, W) bool, C-contiguous
    r0, c0 : int
        The box's first row and column.
    y_row : (h,) float32
        y_n = (v - cy) / fy of the box's rows.
    x_col : (w,) float32
        (u - cx) / fx of the box's columns.
    skew : float32
        s / fx (x = z x_col - skew y).
    points : (N, 3) float32, index : (N,) int64
        Outputs, N at least the number of mask pixels in the box.
    """
    width = depth.shape[1]
    zero = np.float32(0.0)
    inf = np.float32(np.inf)
    count = 0
    for i in range(y_row.shape[0]):
        r = r0 + i
        yn = y_row[i]
        for j in range(x_col.shape[0]):
            c = c0 + j
            z = depth[r, c]
            if mask[r, c] and z > zero and z < inf:
                y = z * yn
                points[count, 0] = z * x_col[j] - skew * y
                points[count, 1] = y
                points[count, 2] = z
                index[count] = r * width + c
                count += 1
    return count


drop_stale_caches(globals())
