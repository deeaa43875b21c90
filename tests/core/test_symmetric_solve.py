"""Tests of fingerps_recon.photometric.symmetric_solve: the symmetric 3x3 solve by the
adjugate, on numpy arrays (the numpy HK solver's use) and on scalars in numba kernels (the
compiled HK and Lambertian kernels' use), against numpy.linalg.solve."""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
import pytest

from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

COUNT = 2000


def _random_spd(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random symmetric positive definite 3x3 matrices (count, 3, 3) (condition
    numbers up to ~1e3) and right-hand sides (count, 3), float64."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    eig = 10.0 ** rng.uniform(-1.5, 1.5, size=(count, 3))
    m = np.einsum("nij,nj,nkj->nik", q, eig, q)
    m = 0.5 * (m + m.transpose(0, 2, 1))
    return m, rng.normal(size=(count, 3))


def _upper(m: np.ndarray) -> tuple[np.ndarray, ...]:
    return m[:, 0, 0], m[:, 0, 1], m[:, 0, 2], m[:, 1, 1], m[:, 1, 2], m[:, 2, 2]


def _numpy_solve(m: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x (count, 3), det (count,)) by the module, on columns of arrays."""
    *adj, det = symmetric_adjugate(*_upper(m))
    x = adjugate_solve(*adj, 1.0 / det, r[:, 0], r[:, 1], r[:, 2])
    return np.stack(x, axis=1), det


def test_numpy_arrays_match_linalg_solve() -> None:
    m, r = _random_spd(COUNT, seed=1)
    x, det = _numpy_solve(m, r)
    expected = np.linalg.solve(m, r[..., None])[..., 0]
    np.testing.assert_allclose(x, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    np.testing.assert_allclose(det, np.linalg.det(m), rtol=1e-9)


def test_adjugate_is_det_times_inverse() -> None:
    m, _ = _random_spd(200, seed=2)
    *adj, det = symmetric_adjugate(*_upper(m))
    c11, c12, c13, c22, c23, c33 = adj
    full = np.stack([np.stack([c11, c12, c13], -1), np.stack([c12, c22, c23], -1),
                     np.stack([c13, c23, c33], -1)], 1)
    np.testing.assert_allclose(full, det[:, None, None] * np.linalg.inv(m), rtol=1e-9,
                               atol=1e-12 * np.abs(full).max())


def test_float32_stays_float32() -> None:
    m, r = _random_spd(COUNT, seed=3)
    m32, r32 = m.astype(np.float32), r.astype(np.float32)
    *adj, det = symmetric_adjugate(*_upper(m32))
    assert det.dtype == np.float32 and all(c.dtype == np.float32 for c in adj)
    x = adjugate_solve(*adj, np.float32(1.0) / det, r32[:, 0], r32[:, 1], r32[:, 2])
    assert all(xi.dtype == np.float32 for xi in x)
    expected = np.linalg.solve(m32.astype(np.float64), r32.astype(np.float64)[..., None])[..., 0]
    # float32 rounding times the condition number (<= ~1e3)
    np.testing.assert_allclose(np.stack(x, 1), expected, rtol=0,
                               atol=2e-3 * np.abs(expected).max())


def test_zero_inverse_determinant_gives_zero_solution() -> None:
    """The callers' guard: a degenerate M (here exactly singular: rank 2) has det 0 and the
    caller passes 0 for 1/det, which gives x = 0."""
    rows = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 1.0], [3.0, 6.0, 4.0]])  # row 3 = row 1 + 2
    m = rows.T @ rows
    *adj, det = symmetric_adjugate(m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2])
    assert abs(det) <= 1e-12 * m[0, 0] * m[1, 1] * m[2, 2]
    assert adjugate_solve(*adj, 0.0, 1.0, -2.0, 3.0) == (0.0, 0.0, 0.0)


def _compiled_solver(parallel: bool) -> Callable[..., None]:
    """A kernel like the reconstruction's (their compile options, kernel_compile; the two
    functions inlined with its ``inline_kernel``): per column, the adjugate solve of the
    float32 upper triangle ``h`` (6, N) and right-hand side ``r`` (3, N), or x = 0 where
    det <= ``singular`` m11 m22 m33 (the HK step's guard)."""
    from fingerps_recon.photometric.kernel_compile import inline_kernel

    adjugate = inline_kernel(symmetric_adjugate)
    solve = inline_kernel(adjugate_solve)
    zero, one = np.float32(0.0), np.float32(1.0)

    def kernel(h, r, singular, x, ok_out):
        for j in numba.prange(h.shape[1]):
            m11, m12, m13 = h[0, j], h[1, j], h[2, j]
            m22, m23, m33 = h[3, j], h[4, j], h[5, j]
            c11, c12, c13, c22, c23, c33, det = adjugate(m11, m12, m13, m22, m23, m33)
            ok = det > singular * m11 * m22 * m33
            inv = one / det
            inv_det = inv if ok else zero
            x[0, j], x[1, j], x[2, j] = solve(c11, c12, c13, c22, c23, c33, inv_det, r[0, j],
                                              r[1, j], r[2, j])
            ok_out[j] = ok

    return numba.njit(parallel=parallel, fastmath=False, error_model="numpy", nogil=True)(
        kernel)


@pytest.mark.parametrize("parallel", [False, True], ids=["serial", "parallel"])
def test_jitted_scalars_match_numpy_and_linalg_solve(parallel: bool) -> None:
    kernel = _compiled_solver(parallel)
    m, r = _random_spd(COUNT, seed=4)
    h = np.stack(_upper(m)).astype(np.float32)
    r32 = np.ascontiguousarray(r.T, dtype=np.float32)
    x = np.empty((3, COUNT), np.float32)
    ok = np.empty(COUNT, bool)
    kernel(h, r32, np.float32(1e-6), x, ok)
    assert ok.all()
    # the same float32 arithmetic as the numpy path, bit for bit (IEEE, no fastmath)
    *adj, det = symmetric_adjugate(*h)
    expected32 = np.stack(adjugate_solve(*adj, np.float32(1.0) / det, *r32))
    np.testing.assert_array_equal(x, expected32)
    m32, r64 = m.astype(np.float32).astype(np.float64), r32.T.astype(np.float64)
    expected = np.linalg.solve(m32, r64[..., None])[..., 0]
    np.testing.assert_allclose(x.T, expected, rtol=0, atol=2e-3 * np.abs(expected).max())


def test_jitted_guard_zeroes_near_singular_matrices() -> None:
    kernel = _compiled_solver(parallel=False)
    m, r = _random_spd(4, seed=5)
    m[1] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])  # rank 1
    m[2] = np.diag([1.0, 1.0, 1e-9])  # tiny det, but relative to the diagonal 1: solved
    m[3] = m[3] + 1e4 * np.outer([1.0, 1.0, 1.0], [1.0, 1.0, 1.0])  # nearly rank 1
    h = np.stack(_upper(m)).astype(np.float32)
    x = np.full((3, 4), np.nan, np.float32)
    ok = np.zeros(4, bool)
    kernel(h, np.ascontiguousarray(r.T, dtype=np.float32), np.float32(1e-6), x, ok)
    assert ok.tolist() == [True, False, True, False]
    np.testing.assert_array_equal(x[:, ~ok], 0.0)
    assert np.isfinite(x).all()
