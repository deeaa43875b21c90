"""The ``FAST`` solver of the masked Poisson equation A h = D^T g (:mod:`surface.integration`,
which states the equations and the preconditioner): float32, the whole mask at once on its
bounding box, in compiled loops.

- One pass over the box computes each pixel's steps from its normal, b, the moments of b and
  the mask's runs (maximal horizontal segments of mask pixels;
  :mod:`surface.integration_rhs_kernel`). From the runs alone come the 4-connected
  components (union-find), the *outline* (the mask pixels with a 4-neighbour in the
  rectangle but outside the mask) and the Gram matrix V^T A V of the monomials s^a t^b,
  1 <= a + b <= 5, in the box's coordinates s, t scaled to [-1, 1] (sums over the mask's
  edges, from prefix sums along the runs; :mod:`surface.integration_topology_kernel`).
- Start: the polynomial q0 = V c closest to the solution in the A-norm, V^T A V c = V^T b:
  the smooth bulk of the surface, exactly the solution when that is such a polynomial (a
  tilted plane costs no iteration; :mod:`surface.integration_polynomials`). The rest,
  A y = b - A q0, by conjugate gradients whose first step is taken whole (step length 1):
  the Frankot–Chellappa solution of the rest on the rectangle. Where a pixel and its four
  neighbours are all in the mask, A equals L, so from then on the residual is zero but on
  the outline pixels: the scalar products, A d and the residual's update cost a few
  thousand pixels, and the next preconditioner input is sparse
  (:mod:`surface.integration_cg_kernel`).
- The preconditioner L^+ (:mod:`surface.integration_preconditioner`): DCTs along the rows and
  a tridiagonal solve down each column.
- End: the polynomial correction closest to the remaining error, V^T A V c = V^T r (the same
  Gram matrix; r on the outline), which takes out most of the smooth error the iterations
  leave. Then each component's mean is taken out and, for a depth, the exponential taken (a
  float64 Taylor polynomial, the exponent halved and the result squared as often as
  needed), in the pass that writes the output: with one component its mean is known
  before (the sums of the directions, kept by the steps, and the mask's moments of the
  polynomial), with several a second pass follows
  (:mod:`surface.integration_solution_kernel`).

Each iteration costs one preconditioner application and one pass over the box. The arrays
of the box are kept per thread for the next call (fresh memory would cost its page faults
every burst).
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.fft

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.surface import integration_preconditioner as preconditioner
from fingerps_recon.surface.integration_cg_kernel import (
    outline_dot,
    outline_laplacian,
    outline_spectrum,
    outline_update,
    take_direction,
)
from fingerps_recon.surface.integration_polynomial_kernel import (
    column_moments,
    outline_moments,
    subtract_poly_laplacian,
)
from fingerps_recon.surface.integration_polynomials import (
    BASIS_A,
    BASIS_B,
    POLY_DEGREE,
    coef_table,
    poly_tables,
    psd_inverse,
)
from fingerps_recon.surface.integration_rhs_kernel import assemble_rhs
from fingerps_recon.surface.integration_solution_kernel import finish_runs, write_solution
from fingerps_recon.surface.integration_steps import Steps
from fingerps_recon.surface.integration_topology_kernel import run_topology

#: The error of a solve whose values come out non-finite.
NON_FINITE = ("normal integration produced non-finite values; check that the normals "
              "inside the mask are finite")


def solve_fast(
    steps: Steps,
    mask: np.ndarray,
    box: tuple[slice, slice],
    *,
    tol: float,
    max_iter: int,
    out: np.ndarray,
    scale: float,
    offset: float,
    exponential: bool,
) -> bool:
    """The ``FAST`` solver (module docstring): writes ``out[box]`` as
    :func:`surface.integration._solve` does and returns True, or returns False (``out``
    untouched) if the relative residual is still above ``tol`` after ``max_iter``
    preconditioner applications."""
    rows, cols = box
    r0, c0 = rows.start, cols.start
    h, w = rows.stop - r0, cols.stop - c0
    shape = (h, scipy.fft.next_fast_len(w, real=True))  # DCT along rows only
    inside = mask.view(np.uint8)
    poly = poly_tables(h, w)
    ws = _workspace(h, w, shape)
    buf = ws.buf  # b, then each preconditioner application's input and output
    n_runs, b_norm2 = assemble_rhs(
        steps.normals, inside, r0, c0, h, w, steps.x_n, steps.y_n, steps.skew, steps.min_nz,
        steps.fx, steps.fy, poly.row_powers, buf, ws.col_moments, ws.run_start, ws.run_stop,
        ws.row_first)
    run_start, run_stop = ws.run_start[:n_runs], ws.run_stop[:n_runs]
    labels = np.empty(n_runs, dtype=np.int32)
    gram = np.empty((BASIS_A.size, BASIS_A.size))
    mask_moments = np.empty((POLY_DEGREE + 1, POLY_DEGREE + 1))
    n_comp, n_out = run_topology(
        run_start, run_stop, ws.row_first, shape[1], poly.pair_prefix, poly.power_prefix,
        poly.row_powers, poly.row_steps, BASIS_A, BASIS_B, labels, ws.outline_rows,
        ws.outline_cols, gram, mask_moments, ws.segments[0], ws.segments[1])
    outline_rows, outline_cols = ws.outline_rows[:n_out], ws.outline_cols[:n_out]

    # The start: the best polynomial of degree <= POLY_DEGREE in the A-norm, q0 = V c,
    # from V^T A V c = V^T b (V^T b: the moments of b).
    gram_inverse = psd_inverse(gram)
    moments = np.empty(BASIS_A.size)
    column_moments(ws.col_moments, poly.col_powers, BASIS_A, BASIS_B, moments)
    coef = gram_inverse @ moments
    r_norm2 = subtract_poly_laplacian(buf, inside, r0, c0, h, w, coef_table(coef),
                                      poly.row_powers, poly.col_powers[1])

    # Conjugate gradients from x = 0 on A x = b - A q0 (module docstring); after the first
    # step (alpha = 1) the residual lives on the outline pixels alone.
    limit = tol * tol * b_norm2
    converged = r_norm2 <= limit
    residual = buf[outline_rows, outline_cols]
    product = np.empty(n_out, dtype=np.float32)
    x, d = ws.x, ws.d
    alpha = np.float32(0.0)
    rz = rz_old = 0.0
    x_sum = 0.0  # the sum of x + alpha d over the mask (for the mean of one component)
    applied = 0  # preconditioner applications, one a step
    cosines = preconditioner.cosines(shape[1])
    pivots = preconditioner.column_pivots(shape)
    while not converged and applied < max_iter:
        preconditioner.precondition(buf, pivots, transformed=applied > 0)
        if applied > 0:
            rz = outline_dot(buf, outline_rows, outline_cols, n_out, residual)
        # the second step restarts (beta = 0): the first one's length was not rz / d_ad
        beta = np.float32(rz / rz_old if applied > 1 and rz_old > 0.0 else 0.0)
        d_sum = take_direction(buf, inside, r0, c0, x, d, alpha, beta, applied)
        d_ad = outline_laplacian(d, inside, r0, c0, outline_rows, outline_cols, n_out,
                                 product)
        if applied > 0 and not d_ad > 0.0:  # no descent left: cannot reach tol
            break
        alpha = np.float32(rz / d_ad if applied > 0 else 1.0)
        x_sum += float(alpha) * d_sum
        r_norm2 = outline_update(residual, product, alpha, n_out)
        rz_old = rz
        applied += 1
        converged = r_norm2 <= limit
        if not converged and applied < max_iter:  # the next step's input, transformed
            outline_spectrum(residual, buf, outline_rows, outline_cols, n_out, cosines)
    if not converged:
        return False
    if applied:  # the best polynomial correction of the remaining error: V^T A V c = V^T r
        outline_moments(residual, outline_rows, outline_cols, n_out, poly.row_powers,
                        poly.col_powers, BASIS_A, BASIS_B, moments)
        coef += gram_inverse @ moments
    table = coef_table(coef)
    counts = np.bincount(labels, weights=run_stop - run_start, minlength=n_comp)
    final = n_comp == 1  # the mean is known: x's sum and q's from the mask's moments
    center = np.array([(x_sum + float(np.sum(table * mask_moments))) / counts[0]])
    sums = np.zeros(n_comp)
    write_solution(x, d, alpha, applied, run_start, run_stop, ws.row_first, labels, table,
                   poly.row_powers, poly.col_powers[1], out, r0, c0, sums, center,
                   float(scale), float(offset), exponential, final)
    if not final:
        center = sums / counts
        finish_runs(out, r0, c0, h, w, run_start, run_stop, ws.row_first, labels, center,
                    float(scale), float(offset), exponential)
    if not np.all(np.isfinite(center)):
        raise FingerpsReconError(NON_FINITE)
    return True


class _Workspace:
    """The FAST solver's arrays for boxes up to a size, kept between calls on one thread
    (fresh memory costs its page faults on every call; the box changes little between
    bursts). Arrays of a call are C-contiguous views of the first elements."""

    def __init__(self) -> None:
        self.capacity = (0, 0, 0)  # h2 * w2, h * w, h

    def fit(self, h: int, w: int, shape: tuple[int, int]) -> None:
        need = (shape[0] * shape[1], h * w, h)
        if any(n > c for n, c in zip(need, self.capacity, strict=True)):
            dct, pixels, rows = (max(n, c) for n, c in zip(need, self.capacity, strict=True))
            self.capacity = (dct, pixels, rows)
            self._buf = np.empty(dct, dtype=np.float32)
            self._x = np.empty(pixels, dtype=np.float32)
            self._d = np.empty(pixels, dtype=np.float32)
            # at most w // 2 + 1 runs a row: h (w // 2 + 1) <= h w / 2 + h
            self._runs = np.empty((2, pixels // 2 + rows + 1), dtype=np.int32)
            self._outline = np.empty((2, pixels), dtype=np.int32)
        deg = POLY_DEGREE
        self.buf = self._buf[: need[0]].reshape(shape)
        self.x = self._x[: need[1]].reshape(h, w)
        self.d = self._d[: need[1]].reshape(h, w)
        self.run_start, self.run_stop = self._runs
        self.outline_rows, self.outline_cols = self._outline
        self.row_first = np.empty(h + 1, dtype=np.int32)
        self.col_moments = np.empty((deg + 1, w))
        self.segments = np.empty((2, 2, w + 1), dtype=np.int32)


_THREAD = threading.local()


def _workspace(h: int, w: int, shape: tuple[int, int]) -> _Workspace:
    """This thread's :class:`_Workspace`, fitted to an h x w box in a DCT box of ``shape``."""
    ws = getattr(_THREAD, "workspace", None)
    if ws is None:
        ws = _THREAD.workspace = _Workspace()
    ws.fit(h, w, shape)
    return ws
