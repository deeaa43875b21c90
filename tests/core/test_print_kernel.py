"""surface.print_kernel against direct numpy statements of the same sums and maps.

Tolerances: float32 kernels to 1e-5 relative of the values' scale (a few float32 roundings of
O(1) terms); float64 ones to 1e-9 (sums of a few hundred O(1) terms, rounded in a different
order).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from fingerps_recon.surface import print_kernel


def test_ridge_laplacian_is_minus_the_divergence_of_the_slopes_on_the_eroded_mask() -> None:
    rng = np.random.default_rng(4)
    h, w = 30, 40
    n = rng.normal(size=(h, w, 3)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) + 0.05  # some below the clamp
    valid = rng.random((h, w)) > 0.1
    valid[:, :3] = True  # the array's edges: outside counts as valid
    signal = np.empty((h, w), dtype=np.float32)
    keep = np.empty((h, w), dtype=bool)
    print_kernel.ridge_laplacian(n, valid, np.float32(0.1), np.float32(0.7), np.float32(1.3),
                                 signal, keep)

    nz = np.maximum(n[..., 2], 0.1)
    mp, mq = n[..., 0] / nz, n[..., 1] / nz
    expected = np.zeros((h, w), dtype=np.float64)
    expected[1:-1, 1:-1] = ((mp[1:-1, 2:] - mp[1:-1, :-2]) * 0.7
                            - (mq[2:, 1:-1] - mq[:-2, 1:-1]) * 1.3)
    eroded = scipy.ndimage.binary_erosion(valid, np.ones((3, 3)), border_value=1)
    expected[~eroded] = 0.0
    np.testing.assert_array_equal(keep, eroded)
    scale = float(np.abs(expected).max())
    np.testing.assert_allclose(signal, expected, rtol=0, atol=1e-5 * scale)


def test_rasterise_interpolates_inside_the_triangles_and_leaves_the_rest() -> None:
    # Two triangles of a square 0..6 (grid units), the values an affine map of the points.
    xy = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])
    values = xy @ np.array([[2.0, 0.5], [-1.0, 3.0]]) + np.array([10.0, -4.0])
    triangles = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    out = np.full((9, 9, 2), np.nan, dtype=np.float32)
    print_kernel.rasterise(xy, values, triangles, out)

    rows, cols = np.mgrid[0:9, 0:9]
    # Grid points within the square, less its lower edges (a box starts past floor(min)).
    inside = (cols >= 1) & (cols <= 6) & (rows >= 1) & (rows <= 6)
    assert np.isfinite(out[inside]).all() and np.isnan(out[~inside]).all()
    points = np.stack([cols[inside], rows[inside]], axis=1).astype(np.float64)
    expected = points @ np.array([[2.0, 0.5], [-1.0, 3.0]]) + np.array([10.0, -4.0])
    np.testing.assert_allclose(out[inside], expected, rtol=0, atol=1e-4)


def test_block_moments_are_the_blocks_sums() -> None:
    rng = np.random.default_rng(5)
    step, h, w = 5, 23, 31  # the last blocks are cut by the image's edge
    depth = (0.09 + 1e-3 * rng.random((h, w))).astype(np.float32)
    valid = rng.random((h, w)) > 0.3
    offsets = (np.arange(step) - (step - 1) / 2.0) / step
    powers = offsets[:, None] ** np.arange(5)
    gh, gw = -(-h // step), -(-w // step)
    mom = np.empty((gh, gw, 5, 5))
    zmom = np.empty((gh, gw, 3, 3))
    print_kernel.block_moments(depth, valid, 90.0, powers, 3, mom, zmom)

    z = np.where(valid, 1e3 * depth.astype(np.float64) - 90.0, 0.0)
    for i in range(gh):
        for j in range(gw):
            rows = slice(i * step, min((i + 1) * step, h))
            cols = slice(j * step, min((j + 1) * step, w))
            dv = powers[: rows.stop - rows.start]  # (rows, P): row offsets' powers
            du = powers[: cols.stop - cols.start]
            m = valid[rows, cols].astype(np.float64)
            np.testing.assert_allclose(mom[i, j], du.T @ m.T @ dv, rtol=0, atol=1e-9)
            np.testing.assert_allclose(zmom[i, j], du[:, :3].T @ z[rows, cols].T @ dv[:, :3],
                                       rtol=0, atol=1e-9)
