"""The closed-form solve of a symmetric 3x3 linear system M x = r by its adjugate (Cramer).

Both per-pixel solves of the reconstruction are symmetric 3x3 systems, one per pixel: the
Lambertian normal equations A b = r of paper Eq. 3 (A = sum_k a_k a_k^T, r = sum_k a_k I_k;
:mod:`photometric.lambertian_kernel`), and the damped Gauss–Newton block
(H + lambda diag(H)) delta = J^T r of the HK least squares, Eq. 6-7
(:mod:`photometric.hk_solver`, :mod:`photometric.hk_step_kernel`). Each is solved in closed
form, M^-1 = adj(M) / det(M), in two parts written here once:

- :func:`symmetric_adjugate`: the upper triangle of adj(M) (the cofactors; adj(M) is
  symmetric too) and det(M), expanded along the first row;
- :func:`adjugate_solve`: x = adj(M) r * inv_det, for a right-hand side r.

Between the two the caller decides what 1 / det(M) is: 1 / det, or 0 where its own test
finds M degenerate (a relative bound on det that differs from solver to solver), which
gives x = 0 there.

The functions are only + - * on their arguments, so the same source serves

- the numba kernels, on float32 scalars: they compile it with
  :func:`photometric.kernel_compile.inline_kernel` (IEEE arithmetic, inlined into their
  per-pixel loops, which LLVM still vectorises);
- the numpy solver, on arrays, element-wise: the results have the arguments' dtype
  (float32 in, float32 out), bit for bit as the kernels' scalars.

No numba here: the numpy solver works without it. Numba keys a kernel's on-disk cache to
the kernel's own source file, so the kernel modules drop their cache when it is older than
this file (:func:`photometric.kernel_compile.drop_stale_caches`).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

# A float (Python or numpy scalar, as in the kernels) or an array of them (the numpy solver).
Value = TypeVar("Value", float, np.floating, np.ndarray)


def symmetric_adjugate(
    m11: Value, m12: Value, m13: Value, m22: Value, m23: Value, m33: Value
) -> tuple[Value, Value, Value, Value, Value, Value, Value]:
    """The adjugate and determinant of the symmetric M = [[m11, m12, m13], [m12, m22, m23],
    [m13, m23, m33]] (its upper triangle given).

    Returns ``(c11, c12, c13, c22, c23, c33, det)``: the upper triangle of adj(M), so that
    M^-1 = adj(M) / det, and det(M) = m11 c11 + m12 c12 + m13 c13. (A flat tuple: numba's
    parallel kernels do not take a nested one apart.)
    """
    c11 = m22 * m33 - m23 * m23
    c12 = m13 * m23 - m12 * m33
    c13 = m12 * m23 - m13 * m22
    c22 = m11 * m33 - m13 * m13
    c23 = m12 * m13 - m11 * m23
    c33 = m11 * m22 - m12 * m12
    det = m11 * c11 + m12 * c12 + m13 * c13
    return c11, c12, c13, c22, c23, c33, det


def adjugate_solve(
    c11: Value, c12: Value, c13: Value, c22: Value, c23: Value, c33: Value, inv_det: Value,
    r1: Value, r2: Value, r3: Value,
) -> tuple[Value, Value, Value]:
    """x = adj(M) r * ``inv_det``: the solution of M x = r for inv_det = 1 / det(M), with
    c11 ... c33 the upper triangle of adj(M) (:func:`symmetric_adjugate`); 0 for inv_det
    gives x = 0."""
    return ((c11 * r1 + c12 * r2 + c13 * r3) * inv_det,
            (c12 * r1 + c22 * r2 + c23 * r3) * inv_det,
            (c13 * r1 + c23 * r2 + c33 * r3) * inv_det)
