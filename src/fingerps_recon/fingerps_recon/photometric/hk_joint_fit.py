"""The HK solve with the global scale A fitted jointly with the pixels (a first burst,
``offline_recon``): the Levenberg–Marquardt loop of ``photometric.hk_solver``'s module
docstring over the whole burst, A's step from the Schur complement, each iteration two
compiled passes over the pixels (``photometric.hk_passes_kernel``)."""

from __future__ import annotations

from types import ModuleType

import numpy as np

from fingerps_recon.photometric.hk_settings import (
    LAMBDA_DOWN,
    LAMBDA_MAX,
    LAMBDA_MIN,
    LAMBDA_START,
    LAMBDA_UP,
    N_SUMS,
)


def fit_jointly(
    passes: JointPasses, *, scale: float | None, iterations: int, tol: float,
) -> tuple[float, list[float], int]:
    """Initialisation and the Levenberg–Marquardt loop (module docstring), in place on the
    state of ``passes``.

    Each iteration is two passes over the pixels: the candidates, their sums and the choice
    at the trial A; then, once the new A is known, the commit fused with the next step.
    ``scale``: A's initial value (None: the global linear fit); A is fitted (a held A is
    solved by :func:`_solve_held`). Returns (A, cost history, iterations done).
    """
    # A and every rho jointly by linear least squares, normals fixed: with the per-pixel
    # sums PP, PC, CC, PI, CI, rho_j(A) = (CI - A PC) / CC and
    # A = sum_j (PI - PC CI / CC) / sum_j (PP - PC^2 / CC). Then rho for the initial A
    # (an A given: the start forms the per-pixel sums itself, without the global ones).
    if scale is None:
        num, den = passes.linear()
        a_scale = max(num / den, 0.0) if den > 0 else 0.0
    else:
        a_scale = float(scale)
    total, *schur = passes.start(a_scale, rows_given=scale is None)
    lam_scale = LAMBDA_START
    history = [total]
    done = 0
    while done < iterations:
        done += 1
        # Joint step: A's part from the Schur complement (hk_step_kernel.steps), then the
        # pixels'.
        trial = a_scale
        g_a, c_delta, d_sum, c_w = schur
        den = d_sum * (1.0 + lam_scale) - c_w
        if den > 1e-12 * d_sum:
            trial = max(a_scale + (g_a - c_delta) / den, 0.0)
        scales = (a_scale, trial)
        # A in closed form for the states chosen at the trial A (the model is linear in
        # A; their cost at A is a known quadratic). The commit re-chooses at that A,
        # which can only lower the cost further. If even so the total would not drop,
        # keep the old A (each pixel then takes the better of its two states there).
        cost, g_sum, d_sum = passes.candidate(scales)
        delta = g_sum / d_sum if d_sum > 0 else 0.0
        best = max(trial + delta, 0.0)
        delta = best - trial
        new_scale, fell_back = best, False
        if cost - delta * (2.0 * g_sum - delta * d_sum) > total:
            new_scale, fell_back = a_scale, True
        lam_scale = (
            min(lam_scale * LAMBDA_UP, LAMBDA_MAX) if fell_back
            else max(lam_scale * LAMBDA_DOWN, LAMBDA_MIN)
        )
        new_total, *schur = passes.commit(scales, at=new_scale)
        a_scale = new_scale
        decrease = total - new_total
        total = new_total
        history.append(total)
        if decrease <= tol * history[-2] and not fell_back:
            break
    return a_scale, history, done


class JointPasses:
    """The per-pixel passes of :func:`fit_jointly` (:mod:`photometric.hk_passes_kernel`), with the
    state they update in place: one compiled, vectorised loop over the chunks of pixels per
    pass, in numba's threads (``numba_threads``), the global sums added up per chunk in a
    fixed order. Each pass returns its global sums: ``linear`` the numerator and
    denominator of A's linear fit; ``start`` and ``commit`` the total cost and the Schur
    parts (P.r, (J^T P).delta0, P.P, (J^T P).w); ``candidate`` the parts of the choice at
    the trial A (chosen cost, P.r, P.P) (``start`` forms the
    linear fit's per-pixel sums itself unless ``linear`` did). ``data``: (meas, views)
    (:func:`_solve`); ``consts`` the kernels' constants (``hk_settings.kernel_consts``);
    ``n`` (3, Np) and ``rho`` (Np,) float32 the initial state."""

    def __init__(
        self, kernel: ModuleType, data: tuple[np.ndarray, ...], *, consts: np.ndarray,
        tau: float, n: np.ndarray, rho: np.ndarray,
    ) -> None:
        f32 = np.float32
        self.kernel, self.data, self.n, self.rho = kernel, data, n, rho
        count = rho.size
        self.chunks = count // kernel.CHUNK
        self.tau = tau
        self.neg_tau = f32(-tau)
        self.consts = consts
        self.lam = np.full(count, LAMBDA_START, f32)
        self.sums = np.zeros((N_SUMS, count), f32)
        self.sums_new = np.zeros((N_SUMS, count), f32)
        self.n_new = np.empty_like(n)
        self.rho_new = np.empty_like(rho)
        self.delta0 = np.zeros((3, count), f32)
        self.w = np.zeros((3, count), f32)
        self.rows = np.zeros((5, count), f32)

    def _parts(self, width: int) -> np.ndarray:
        return np.zeros((self.chunks, width), np.float64)

    def _a_tau(self, scale: float) -> np.float32:
        return np.float32(scale * self.tau)

    def linear(self) -> list[float]:
        parts = self._parts(2)
        self.kernel.linear_sums(self.n, *self.data, self.neg_tau, self.consts, self.rows, parts)
        return [float(v) for v in parts.sum(axis=0)]

    def start(self, scale: float, *, rows_given: bool) -> list[float]:
        parts = self._parts(5)
        self.kernel.start(self.n, self.rho, self.lam, self.rows, float(scale),
                          self._a_tau(scale), self.neg_tau, *self.data, self.consts,
                          self.sums, self.delta0, self.w, parts, rows_given)
        total = [float(v) for v in parts.sum(axis=0)]
        return total

    def candidate(self, scales: tuple[float, float]) -> list[float]:
        parts = self._parts(3)
        self.kernel.candidate(self.n, self.rho, self.delta0, self.w, float(scales[0]),
                              float(scales[1]), self._a_tau(scales[1]), self.neg_tau,
                              *self.data, self.consts, self.sums, self.n_new, self.rho_new,
                              self.sums_new, parts)
        return [float(v) for v in parts.sum(axis=0)]

    def commit(self, scales: tuple[float, float], *, at: float) -> list[float]:
        parts = self._parts(5)
        self.kernel.commit(self.n, self.rho, self.lam, float(scales[0]), float(scales[1]),
                           float(at), self.consts, self.sums, self.n_new, self.rho_new,
                           self.sums_new, self.delta0, self.w, parts)
        total = [float(v) for v in parts.sum(axis=0)]
        return total
