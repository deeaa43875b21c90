"""Photometric stereo under the simplified Hanrahan–Krueger skin model (paper Eq. 6-7).

Problem (NOTES §2). Per pixel j and light k the model of :mod:`fingerps_recon.photometric.hk_model`
(paper Eq. 4 with the typos mended), times the light's relative intensity e_k::

    f_jk = e_k * [A * p(c, g) * c_i / (c_i + c_r) * (1 - exp(-tau_d (1/c_i + 1/c_r))) + rho_j * c_i]

with c_i = l_jk . n_j, c_r = v_j . n_j, and f = 0 where c_i <= 0 (attached shadow) or
c_r <= 0. The unknowns are each pixel's unit normal n_j (2 degrees of freedom) and albedo
rho_j, and one global scale A; d, sigma_s, sigma_a and g are fixed (``SkinParams``, default
the paper's finger values), as in the paper's experiments. The solver minimises
E = sum_jk (I_jk - f_jk)^2 (Eq. 6-7) over the usable measurements (not shadowed, not
saturated). Phase function: the cosine of the scattering angle follows
``SkinParams.phase`` -- ``PhaseConvention.PHYSICAL`` (c = -l.v, the default) or ``PAPER``
(c = l.v, the paper's Eq. 5 as printed); see :mod:`fingerps_recon.photometric.hk_model`.

Method. Batched Levenberg–Marquardt over all pixels at once (the paper uses a neural-network
solver on dE/dx = 0; any method reaching the same minimum serves, NOTES §2):

- per pixel the unknowns are a step (a, b) along the tangent directions t_x = e_x - n_x n,
  t_y = e_y - n_y n (a basis of the tangent plane wherever n_z != 0), then
  n <- normalize(n + a t_x + b t_y), and a step in rho; the analytic Jacobian columns are
  df/dc_i (l . t) + df/dc_r (v . t), with l . t_x = l_x - c_i n_x, and e_k c_i;
- the normal equations form an "arrow": one 3x3 block per pixel plus one row and column for
  A. A's step comes from the Schur complement (the per-pixel 3x3 blocks inverted in closed
  form by their adjugate, vectorised), so (n, rho, A) take one joint Gauss–Newton step --
  A, rho and n are strongly coupled (the Lommel–Seeliger factor c_i / (c_i + c_r) is nearly
  proportional to c_i where c_r ~ 1, and a change of A moves the normals), so updating
  them in turn would zigzag;
- each pixel keeps the better of its state and its candidate (its own damping factor,
  Marquardt scaling); then A is set in closed form for the kept states (the model is
  linear in A, and every pixel's cost is a known quadratic in A), which is an exact line
  minimisation in A; if the joint step in A does not pay, A is kept. The total cost never
  increases (``cost_history``). Stop after ``iterations`` or once an iteration lowers the
  cost by less than ``tol`` times it;
- initialisation as in the paper: n and rho from the Lambertian solution (Eq. 3), A from a
  global linear least-squares fit of A and every rho_j jointly with the normals fixed,
  then rho in closed form for that A.

The derivatives dS/dc_i and dS/dc_r of S = c_i / (c_i + c_r) (1 - E) contain 1/c_i and 1/c_r
and blow up as c_i or c_r -> 0; those factors are capped at 1 / ``_DERIVATIVE_FLOOR`` (the
model values are not changed), so the Jacobian stays finite. The optical-depth exponential
E = exp(-tau_d (1/c_i + 1/c_r)) is evaluated exactly: for the finger constants it is below
3e-4 at every angle (tau_d (1/c_i + 1/c_r) >= 2 tau_d = 8.3, never above the 30 at which it
could be dropped), small but not negligible at float32 precision.

Arithmetic and speed. Two backends (``solve_hk(backend=...)``) run the same algorithm, the
same host logic (:func:`_minimise`) over the same per-pixel passes, in float32 per
measurement; the per-pixel sums and state are float32, A and the totals float64. float32
limits how closely a pixel's minimum is approached: its cost stays within about 1e-6
(relative) of the float64 optimum.

- "numpy" (the reference): the per-measurement work (about 60 passes over (K, N) arrays per
  iteration) in blocks of ``_BLOCK`` pixels with per-thread workspaces reused from block to
  block, in up to :func:`fingerps_recon.photometric.kernel_threads.thread_limit` threads.
- "numba" (:mod:`fingerps_recon.photometric.hk_kernel`): each pass one compiled loop over chunks of
  pixels (vectorised, in up to that many numba threads), the gathering of the
  masked pixels and the result images too. On the rig finger (~172 000 pixels x 7 lights,
  two cores) 3-4x faster than numpy; the two agree to float32 rounding (normals within
  1e-4 degrees, A within 1e-7). The first call in a process compiles the kernels or loads
  them from numba's on-disk cache (:mod:`fingerps_recon.photometric.kernel_warm_up`).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from types import ModuleType
from typing import Protocol, TypeVar

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.hk_model import PhaseConvention, SkinParams, henyey_greenstein
from fingerps_recon.photometric.kernel_threads import numba_threads, thread_limit
from fingerps_recon.photometric.light_intensities import checked_intensities
from fingerps_recon.photometric.symmetric_solve import adjugate_solve, symmetric_adjugate

# 1/c_i and 1/c_r in the derivatives are capped at 1 / _DERIVATIVE_FLOOR.
_DERIVATIVE_FLOOR = 1e-3
# Smallest c_i used where the model is evaluated (avoids 1/0; changes f by < 1e-12 A p).
_VALUE_FLOOR = 1e-12
# Initial normals facing away from the camera (v.n below this) are tilted to it.
_MIN_INIT_CR = 0.05
# Levenberg–Marquardt damping: start, decrease on success, increase on failure, bounds.
_LAMBDA_START = 1e-3
_LAMBDA_DOWN = 1.0 / 3.0
_LAMBDA_UP = 10.0
_LAMBDA_MIN = 1e-9
_LAMBDA_MAX = 1e9
# Row of each per-pixel sum (_Evaluator.block_sums, _State.sums).
_H11, _H12, _H13, _H22, _H23, _H33, _G1, _G2, _G3, _C1, _C2, _C3, _D, _GA, _COST = range(15)
_N_SUMS = 15
# Pixels per block of the evaluation (workspace buffers (K, _BLOCK) float32 stay in cache).
_BLOCK = 16384
_T = TypeVar("_T")
# solve_hk's backends, and the outcome of importing the numba kernels (module or None, and
# the reason it failed), tried once per process.
_BACKENDS = ("auto", "numba", "numpy")
_KERNEL: list[ModuleType | None] = []
_KERNEL_ERROR: list[str] = [""]


def _kernel_module(backend: str) -> ModuleType | None:
    """:mod:`photometric.hk_kernel` if ``backend`` is "numba" or "auto" and numba can be
    imported, else None (the numpy backend)."""
    if backend == "numpy":
        return None
    if not _KERNEL:
        try:
            _KERNEL.append(importlib.import_module(f"{__package__}.hk_kernel"))
        except Exception as exc:  # ImportError, or numba failing to set itself up
            _KERNEL.append(None)
            _KERNEL_ERROR[0] = f"{type(exc).__name__}: {exc}"
    return _KERNEL[0]


@dataclass(frozen=True)
class HKResult:
    """Result of :func:`solve_hk`.

    Attributes
    ----------
    normals : (H, W, 3) float32
        Unit normals, PS frame; zeros where not ``valid``.
    albedo : (H, W) float32
        rho of the Lambertian (multiple-scattering) term, image units per unit relative
        intensity; zeros where not ``valid``.
    scale : float
        The global scale A of the single-scattering term (fitted, or the fixed value given);
        NaN if it was to be fitted but no pixel was valid.
    valid : (H, W) bool
        Pixels inside the mask with at least 3 usable measurements, a usable initial normal
        and albedo, and a finite, determined solution (non-singular J^T J there).
    residual_rms : (H, W) float32
        Root mean square of I - f over each pixel's usable measurements at the solution, in
        image units; zeros where not ``valid``.
    iterations : int
        Levenberg–Marquardt iterations performed.
    cost_history : tuple of float
        Total cost E = sum (I - f)^2 over the valid pixels' usable measurements, after the
        initialisation and after each iteration; non-increasing.
    """

    normals: np.ndarray
    albedo: np.ndarray
    scale: float
    valid: np.ndarray
    residual_rms: np.ndarray
    iterations: int
    cost_history: tuple[float, ...]


def solve_hk(
    images: np.ndarray,
    lights: np.ndarray,
    *,
    mask: np.ndarray,
    init_normals: np.ndarray,
    init_albedo: np.ndarray,
    views: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
    intensities: np.ndarray | None = None,
    usable: np.ndarray | None = None,
    params: SkinParams = SkinParams(),  # noqa: B008 (frozen dataclass)
    scale: float | None = None,
    iterations: int = 10,
    tol: float = 1e-6,
    backend: str = "auto",
) -> HKResult:
    """Normals, albedo and the global scale A under the simplified HK model (Eq. 6-7).

    See the module docstring for the model and the method. The phase function's
    scattering-angle convention is ``params.phase`` (``PhaseConvention.PHYSICAL`` by
    default: c = -l.v).

    Parameters
    ----------
    images : (K, H, W) float or int
        One image per light, linear, flat-field corrected and dark-subtracted.
    lights : (K, 3) or (K, H, W, 3) float
        Unit directions from the surface towards each light, PS frame: distant lights, or
        one direction per pixel (near lights). Normalised here.
    mask : (H, W) bool
        Pixels to solve.
    init_normals : (H, W, 3) float
        Initial unit normals (PS frame), e.g. ``solve_lambertian(...).normals``; pixels whose
        initial normal is zero or not finite are invalid. Initial normals facing away from
        the camera are tilted towards it first.
    init_albedo : (H, W) float
        Initial albedo, e.g. ``solve_lambertian(...).albedo``; pixels where it is not finite
        are invalid. rho is re-fitted in closed form (given the initial normals and the
        initial A) before the first iteration, so this is only a fall-back.
    views : (3,) or (H, W, 3) float
        Unit directions from the surface towards the camera, PS frame: (0, 0, 1) for an
        orthographic camera, one per pixel for a perspective one (minus the pixel's ray).
    intensities : (K,) or (K, H, W) float, optional
        Relative light intensities e_k > 0 (they scale both terms), one per light or one
        per light and pixel (near lights: e.g. the flat field's irradiance, so that the
        images need not be divided by it and keep their noise uniform); default all ones.
        Per-pixel values that are not finite or <= 0 leave that measurement out.
    usable : (K, H, W) bool, optional
        Measurements to use (False for shadowed or saturated ones). Default: finite and
        > 0. Pixels with fewer than 3 usable measurements are invalid.
    params : SkinParams
        d, sigma_s, sigma_a, g (fixed) and the phase convention.
    scale : float, optional
        None: fit A (>= 0). A number >= 0: keep A fixed at it.
    iterations : int
        Maximum number of Levenberg–Marquardt iterations, >= 0.
    tol : float
        Stop when an iteration lowers the total cost by less than ``tol`` times it, >= 0.
    backend : {"auto", "numba", "numpy"}
        Where the per-pixel passes run: "numba", compiled loops
        (:mod:`photometric.hk_kernel`; needs numba); "numpy", the reference (vectorised
        passes over blocks of pixels); "auto", numba when it can be imported, else numpy.
        The same algorithm and minimum either way (results agree to float32 rounding). The
        first numba call in a process compiles or loads the kernels
        (:mod:`fingerps_recon.photometric.kernel_warm_up`).

    Returns
    -------
    HKResult

    Raises
    ------
    FingerpsReconError
        On inconsistent shapes, fewer than 3 lights, non-finite or zero light directions,
        non-positive intensities, or bad options (``backend="numba"`` without numba). The
        inputs are not modified.
    """
    if backend not in _BACKENDS:
        raise FingerpsReconError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    if backend == "numba" and _kernel_module("numba") is None:
        raise FingerpsReconError(
            f"backend='numba' but the numba kernels cannot be imported ({_KERNEL_ERROR[0]}); "
            "install numba (requirements.txt) or use backend='numpy' or 'auto'"
        )
    if scale is not None and not (
        isinstance(scale, (int, float, np.integer, np.floating))
        and math.isfinite(scale) and scale >= 0
    ):
        raise FingerpsReconError(f"scale must be None (fit A) or a finite number >= 0, got {scale}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or (
        iterations < 0
    ):
        raise FingerpsReconError(f"iterations must be an integer >= 0, got {iterations!r}")
    if not (
        isinstance(tol, (int, float, np.integer, np.floating)) and math.isfinite(tol) and tol >= 0
    ):
        raise FingerpsReconError(f"tol must be a finite number >= 0, got {tol}")
    inputs = _check(
        images, lights, mask=mask, init_normals=init_normals, init_albedo=init_albedo,
        views=views, intensities=intensities, usable=usable, params=params,
    )
    kernel = _kernel_module(backend)
    fit, iterations, tol = scale is None, int(iterations), float(tol)
    if kernel is not None:
        with numba_threads():
            return _solve_numba(inputs, kernel, scale=scale, fit=fit, iterations=iterations,
                                tol=tol)
    columns, pix, (h, w) = _prepare(inputs)
    if pix.size == 0:
        return _nothing_valid((h, w), scale)
    with _NumpyPasses(columns) as passes:
        a_scale, history, done = _minimise(
            passes, scale=scale, fit=fit, iterations=iterations, tol=tol,
        )
        n, rho, sums = passes.result(pix.size)
    cost = sums[_COST]
    ok = np.all(np.isfinite(n), axis=0) & np.isfinite(rho) & _determined(sums)
    normals = np.zeros((h * w, 3), np.float32)
    albedo = np.zeros(h * w, np.float32)
    rms = np.zeros(h * w, np.float32)
    valid = np.zeros(h * w, bool)
    normals[pix[ok]] = n[:, ok].T
    albedo[pix[ok]] = rho[ok]
    rms[pix[ok]] = np.sqrt(np.maximum(cost[ok], 0.0) / columns.counts[ok])
    valid[pix[ok]] = True
    return HKResult(
        normals=normals.reshape(h, w, 3), albedo=albedo.reshape(h, w), scale=float(a_scale),
        valid=valid.reshape(h, w), residual_rms=rms.reshape(h, w), iterations=done,
        cost_history=tuple(history),
    )


def _nothing_valid(shape: tuple[int, int], scale: float | None) -> HKResult:
    h, w = shape
    return HKResult(
        normals=np.zeros((h, w, 3), np.float32), albedo=np.zeros((h, w), np.float32),
        scale=float("nan") if scale is None else float(scale),
        valid=np.zeros((h, w), bool), residual_rms=np.zeros((h, w), np.float32),
        iterations=0, cost_history=(0.0,),
    )


def _solve_numba(
    inputs: _Inputs, kernel: ModuleType, *, scale: float | None, fit: bool, iterations: int,
    tol: float,
) -> HKResult:
    """solve_hk with the numba backend: the pixels gathered (as :func:`_prepare`), the
    passes, and the result images, each a compiled loop over the pixels."""
    _, h, w = inputs.images.shape
    gathered = _gather_numba(inputs, kernel)
    if gathered is None:
        return _nothing_valid((h, w), scale)
    pix, counts, data, n0, rho0 = gathered
    passes = _NumbaPasses(kernel, data, tau=float(inputs.params.optical_depth), n=n0,
                          rho=rho0)
    a_scale, history, done = _minimise(
        passes, scale=scale, fit=fit, iterations=iterations, tol=tol,
    )
    normals = np.zeros((h * w, 3), np.float32)
    albedo = np.zeros(h * w, np.float32)
    rms = np.zeros(h * w, np.float32)
    valid = np.zeros(h * w, bool)
    kernel.finish(pix, passes.n, passes.rho, passes.sums, counts, normals, albedo, rms, valid)
    return HKResult(
        normals=normals.reshape(h, w, 3), albedo=albedo.reshape(h, w), scale=float(a_scale),
        valid=valid.reshape(h, w), residual_rms=rms.reshape(h, w), iterations=done,
        cost_history=tuple(history),
    )


def _float_array(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``a`` reshaped, C-contiguous, float32 or float64 (other dtypes as float64): the
    dtypes the gather kernels are compiled for."""
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    return np.ascontiguousarray(a).reshape(shape)


def _gather_numba(
    inputs: _Inputs, kernel: ModuleType,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...], np.ndarray, np.ndarray] | None:
    """The solvable pixels in the numba passes' layout, as :func:`_prepare` gathers them
    for the numpy backend (the same pixels, values and checks): (their flat indices (N,),
    usable measurements (N,) float64, the passes' data (values, usable, lights, views,
    intensity, phase), initial normals (3, N) float32, albedo (N,) float32), or None if
    there are none."""
    imgs, m, e, vw = inputs.images, inputs.mask, inputs.intensities, inputs.views
    k, h, w = imgs.shape
    f32 = np.float32
    if imgs.dtype not in (np.float32, np.float64):  # (integers: exact in float32, as below)
        imgs = imgs.astype(f32)
    imgs = np.ascontiguousarray(imgs).reshape(k, h * w)
    use_in = (
        np.ones((1, 1), bool) if inputs.usable is None
        else np.ascontiguousarray(inputs.usable).reshape(k, h * w)
    )
    e_in = _float_array(e, (k, h * w) if e.ndim == 3 else (k, 1))
    n_in = _float_array(inputs.normals, (h * w, 3))
    rho_in = _float_array(inputs.albedo, (h * w,))
    cand = np.flatnonzero(m)
    keep = np.empty(cand.size, bool)
    counts = np.empty(cand.size, np.int32)
    kernel.select_pixels(cand, imgs, use_in, e_in, n_in, rho_in, keep, counts)
    pix = cand if keep.all() else cand[keep]
    count = pix.size
    if count == 0:
        return None

    # Directions, e and e p shared by all pixels, as _prepare forms them; the rest per pixel.
    params = inputs.params
    per_pixel_lights, per_pixel_views = inputs.per_pixel_lights, vw.ndim == 3
    # (C-contiguous, as the per-pixel ones: one compiled version of the passes.)
    l_dirs = (np.empty((3, k, count), f32) if per_pixel_lights
              else np.ascontiguousarray(inputs.lights.T[:, :, None], f32))
    v_dirs = (np.empty((3, count), f32) if per_pixel_views
              else np.ascontiguousarray(vw[:, None], f32))
    inten = (np.empty((k, count), f32) if e.ndim == 3
             else np.ascontiguousarray(e[:, None], f32))
    if per_pixel_lights or per_pixel_views or e.ndim == 3:
        phase = np.empty((k, count), f32)
    else:
        c_phi = _dot3(l_dirs, v_dirs[:, None, :])
        c_sc = -c_phi if params.phase is PhaseConvention.PHYSICAL else c_phi
        phase = np.ascontiguousarray(inten * henyey_greenstein(np.clip(c_sc, -1, 1), params.g))
    g = f32(params.g)
    hg = np.array([1 + g * g, 2 * g, 1 - g * g, f32(4 * math.pi)], f32)
    lights_in = (_float_array(inputs.lights, (k, h * w, 3)) if per_pixel_lights
                 else np.zeros((1, 1, 3), f32))
    views_in = _float_array(vw, (h * w, 3)) if per_pixel_views else np.zeros((1, 3), f32)
    values = np.empty((k, count), f32)
    use = np.empty((k, count), bool)
    n0 = np.empty((3, count), f32)
    rho0 = np.empty(count, f32)
    counts_out = np.empty(count, np.float64)
    bad = np.zeros(count, np.uint8)
    kernel.gather(pix, imgs, use_in, e_in, n_in, rho_in, lights_in, views_in, hg,
                  params.phase is PhaseConvention.PHYSICAL, _MIN_INIT_CR, values, use, inten,
                  phase, l_dirs, v_dirs, n0, rho0, counts_out, bad)
    if per_pixel_lights or per_pixel_views:
        flags = int(np.bitwise_or.reduce(bad))
        for name, non_finite, zero in (
            ("lights", kernel.BAD_LIGHT, kernel.ZERO_LIGHT),
            ("views", kernel.BAD_VIEW, kernel.ZERO_VIEW),
        ):  # the messages of _unit_columns
            if flags & non_finite:
                raise FingerpsReconError(
                    f"{name} contain non-finite values inside the mask; check the calibration"
                )
            if flags & zero:
                raise FingerpsReconError(f"{name} contain zero vectors inside the mask")
    return pix, counts_out, (values, use, l_dirs, v_dirs, inten, phase), n0, rho0


@dataclass(frozen=True)
class _Data:
    """Measurements of the N valid pixels and the constants of the forward model.

    Pixels are padded to ``blocks * _BLOCK`` (padding pixels have no usable measurement)
    and stored by block: per-measurement arrays are (blocks, K, B) float32 (``phase`` and
    ``intensity`` are (K, 1) when they do not vary with the pixel), per-pixel lights
    (blocks, 3, K, B), distant lights (K, 3); views (3, 1), or (3, N_padded) per pixel.
    """

    values: np.ndarray  # I where usable, else 0
    usable: np.ndarray  # bool
    counts: np.ndarray  # (N,) float64, usable measurements per pixel
    lights: np.ndarray
    per_pixel_lights: bool
    views: np.ndarray
    intensity: np.ndarray  # e_k, (K, 1), or (blocks, K, B) per pixel
    phase: np.ndarray  # e_k p(c, g)
    tau: float

    @property
    def blocks(self) -> int:
        return int(self.values.shape[0])


@dataclass(frozen=True)
class _State:
    """Per-pixel unknowns and sums (padded length), updated in place block by block.

    ``sums`` rows are indexed by ``_H11`` ... ``_COST`` (:meth:`_Evaluator.block_sums`); the
    ``*_new`` arrays hold the candidate of the current iteration, ``delta0`` and ``w`` its
    step (:func:`_block_step`).
    """

    n: np.ndarray  # (3, Np) float32 unit normals
    rho: np.ndarray  # (Np,) float32
    lam: np.ndarray  # (Np,) float32 damping factors
    sums: np.ndarray  # (15, Np) float32
    n_new: np.ndarray
    rho_new: np.ndarray
    sums_new: np.ndarray
    delta0: np.ndarray  # (3, Np) float32
    w: np.ndarray  # (3, Np) float32

    @classmethod
    def start(cls, n: np.ndarray, rho: np.ndarray) -> _State:
        size = rho.size
        n, rho = n.astype(np.float32), rho.astype(np.float32)
        return cls(
            n=n, rho=rho, lam=np.full(size, _LAMBDA_START, np.float32),
            sums=np.zeros((_N_SUMS, size), np.float32), n_new=np.empty_like(n),
            rho_new=np.empty_like(rho), sums_new=np.zeros((_N_SUMS, size), np.float32),
            delta0=np.zeros((3, size), np.float32), w=np.zeros((3, size), np.float32),
        )


def _minimise(
    passes: _Passes, *, scale: float | None, iterations: int, tol: float, fit: bool = True,
) -> tuple[float, list[float], int]:
    """Initialisation and the Levenberg–Marquardt loop (module docstring), in place on the
    state of ``passes`` (either backend: the same host logic, the same per-pixel passes).

    Each iteration is two passes over the pixels: the candidates, their sums and the choice
    at the trial A; then, once the new A is known, the commit fused with the next step.
    ``scale``: A's initial value (None: the global linear fit); ``fit``: whether A is
    fitted or kept. Returns (A, cost history, iterations done).
    """
    # A and every rho jointly by linear least squares, normals fixed: with the per-pixel
    # sums PP, PC, CC, PI, CI, rho_j(A) = (CI - A PC) / CC and
    # A = sum_j (PI - PC CI / CC) / sum_j (PP - PC^2 / CC). Then rho for the initial A.
    num, den = passes.linear()
    if scale is None:
        a_scale = max(num / den, 0.0) if den > 0 else 0.0
    else:
        a_scale = float(scale)
    total, *schur = passes.start(a_scale, fit=fit)
    lam_scale = _LAMBDA_START
    history = [total]
    done = 0
    while done < iterations:
        done += 1
        # Joint step: A's part from the Schur complement (_block_step), then the pixels'.
        trial = a_scale
        if fit:
            g_a, c_delta, d_sum, c_w = schur
            den = d_sum * (1.0 + lam_scale) - c_w
            if den > 1e-12 * d_sum:
                trial = max(a_scale + (g_a - c_delta) / den, 0.0)
        scales = (a_scale, trial)
        parts = passes.candidate(scales, fit=fit)
        new_scale, fell_back = trial, False
        if fit:
            # A in closed form for the states chosen at the trial A (the model is linear in
            # A; their cost at A is a known quadratic). The commit re-chooses at that A,
            # which can only lower the cost further. If even so the total would not drop,
            # keep the old A (each pixel then takes the better of its two states there).
            cost, g_sum, d_sum = parts
            delta = g_sum / d_sum if d_sum > 0 else 0.0
            best = max(trial + delta, 0.0)
            delta = best - trial
            new_scale = best
            if cost - delta * (2.0 * g_sum - delta * d_sum) > total:
                new_scale, fell_back = a_scale, True
            lam_scale = (
                min(lam_scale * _LAMBDA_UP, _LAMBDA_MAX) if fell_back
                else max(lam_scale * _LAMBDA_DOWN, _LAMBDA_MIN)
            )
        new_total, *schur = passes.commit(scales, at=new_scale, fit=fit)
        a_scale = new_scale
        decrease = total - new_total
        total = new_total
        history.append(total)
        if decrease <= tol * history[-2] and not fell_back:
            break
    return a_scale, history, done


class _Passes(Protocol):
    """The per-pixel passes of :func:`_minimise`, with the state they update in place.

    Each pass returns its global sums (float): ``linear`` the numerator and denominator of
    A's linear fit; ``start`` and ``commit`` the total cost and the Schur parts of
    :func:`_block_step` (P.r, (J^T P).delta0, P.P, (J^T P).w); ``candidate`` the parts of
    the choice at the trial A (chosen cost, P.r, P.P), or nothing if A is fixed.
    """

    def linear(self) -> list[float]: ...

    def start(self, scale: float, *, fit: bool) -> list[float]: ...

    def candidate(self, scales: tuple[float, float], *, fit: bool) -> list[float]: ...

    def commit(self, scales: tuple[float, float], *, at: float, fit: bool) -> list[float]: ...


class _NumpyPasses:
    """The passes of the numpy backend: blocks of ``_BLOCK`` pixels in worker threads
    (:class:`_Evaluator`). A context manager (the thread pool is shut down on exit)."""

    def __init__(self, columns: _Columns) -> None:
        data, n0, rho0 = columns.pack()
        self.st = _State.start(n0, rho0)
        self.ev = _Evaluator(data)

    def __enter__(self) -> _NumpyPasses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.ev.__exit__(*exc)

    def linear(self) -> list[float]:
        return _total(self.ev.map(partial(_block_linear, ev=self.ev, st=self.st)))

    def start(self, scale: float, *, fit: bool) -> list[float]:
        return _total(self.ev.map(
            partial(_block_start, ev=self.ev, st=self.st, scale=scale, fit=fit)
        ))

    def candidate(self, scales: tuple[float, float], *, fit: bool) -> list[float]:
        return _total(self.ev.map(
            partial(_block_candidate, ev=self.ev, st=self.st, scales=scales, fit=fit)
        ))

    def commit(self, scales: tuple[float, float], *, at: float, fit: bool) -> list[float]:
        return _total(self.ev.map(
            partial(_block_commit, st=self.st, scales=scales, at=at, fit=fit)
        ))

    def result(self, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        st = self.st
        return st.n[:, :count], st.rho[:count], st.sums[:, :count].astype(np.float64)


class _NumbaPasses:
    """The passes of the numba backend (:mod:`fingerps_recon.photometric.hk_kernel`): one compiled,
    vectorised loop over the pixels per pass, in numba's threads (``numba_threads``),
    the global sums added up per chunk of pixels in a fixed order. ``data``: the gathered
    (values, usable, lights, views, intensity, phase) (:func:`_gather_numba`); ``n`` (3, N)
    and ``rho`` (N,) float32 the initial state (updated in place)."""

    def __init__(
        self, kernel: ModuleType, data: tuple[np.ndarray, ...], *, tau: float, n: np.ndarray,
        rho: np.ndarray,
    ) -> None:
        f32 = np.float32
        self.kernel, self.data, self.n, self.rho = kernel, data, n, rho
        count = rho.size
        self.chunks = max(1, -(-count // kernel.CHUNK))
        self.tau = tau
        self.neg_tau = f32(-tau)
        consts = np.zeros(kernel.N_CONSTS, f32)
        for index, value in (
            (kernel.VALUE_FLOOR, _VALUE_FLOOR), (kernel.DERIVATIVE_FLOOR, _DERIVATIVE_FLOOR),
            (kernel.LAMBDA_DOWN, _LAMBDA_DOWN), (kernel.LAMBDA_UP, _LAMBDA_UP),
            (kernel.LAMBDA_MIN, _LAMBDA_MIN), (kernel.LAMBDA_MAX, _LAMBDA_MAX),
        ):
            consts[index] = value
        self.consts = consts
        self.lam = np.full(count, _LAMBDA_START, f32)
        self.sums = np.zeros((_N_SUMS, count), f32)
        self.sums_new = np.zeros((_N_SUMS, count), f32)
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

    def start(self, scale: float, *, fit: bool) -> list[float]:
        parts = self._parts(5)
        self.kernel.start(self.n, self.rho, self.lam, self.rows, float(scale),
                          self._a_tau(scale), self.neg_tau, *self.data, self.consts,
                          self.sums, self.delta0, self.w, parts)
        total = [float(v) for v in parts.sum(axis=0)]
        return total if fit else total[:1]

    def candidate(self, scales: tuple[float, float], *, fit: bool) -> list[float]:
        parts = self._parts(3)
        self.kernel.candidate(self.n, self.rho, self.delta0, self.w, float(scales[0]),
                              float(scales[1]), self._a_tau(scales[1]), self.neg_tau,
                              *self.data, self.consts, self.sums, self.n_new, self.rho_new,
                              self.sums_new, parts)
        return [float(v) for v in parts.sum(axis=0)] if fit else []

    def commit(self, scales: tuple[float, float], *, at: float, fit: bool) -> list[float]:
        parts = self._parts(5)
        self.kernel.commit(self.n, self.rho, self.lam, float(scales[0]), float(scales[1]),
                           float(at), self.consts, self.sums, self.n_new, self.rho_new,
                           self.sums_new, self.delta0, self.w, parts)
        total = [float(v) for v in parts.sum(axis=0)]
        return total if fit else total[:1]


def _total(parts: list[tuple[float, ...]]) -> list[float]:
    """Element-wise sum of the blocks' partial sums."""
    return [float(sum(values)) for values in zip(*parts, strict=True)]


def _block_linear(
    ws: dict[str, np.ndarray], block: int, *, ev: _Evaluator, st: _State
) -> tuple[float, float]:
    """Linear sums PP, PC, CC, PI, CI of a block into ``st.sums_new`` rows 0-4; returns the
    block's parts of the numerator and denominator of A's linear fit."""
    sl = _block_slice(block)
    p, c = ev.block_values(ws, block, st.n[:, sl])
    vals = ev.data.values[block]
    rows = st.sums_new[:5, sl]
    for row, (a, b) in enumerate(((p, p), (p, c), (c, c), (p, vals), (c, vals))):
        np.einsum("kn,kn->n", a, b, out=rows[row])
    pp, pc, cc, p_i, c_i = rows.astype(np.float64)
    cc = np.maximum(cc, 1e-30)
    return float(np.sum(p_i - pc * c_i / cc)), float(np.sum(pp - pc * pc / cc))


def _block_start(
    ws: dict[str, np.ndarray], block: int, *, ev: _Evaluator, st: _State, scale: float,
    fit: bool,
) -> tuple[float, ...]:
    """rho in closed form given A and the initial normals (rows 0-4 of ``st.sums_new``), the
    sums there, and the first step. Returns (cost, Schur parts of :func:`_block_step`)."""
    sl = _block_slice(block)
    _, pc, cc, _, c_i = st.sums_new[:5, sl].astype(np.float64)
    fitted = np.maximum((c_i - scale * pc) / np.maximum(cc, 1e-30), 0.0)
    st.rho[sl] = np.where(cc > 0, fitted, st.rho[sl])
    ev.block_sums(ws, block, n=st.n, rho=st.rho, scale=scale, out=st.sums, with_scale=fit)
    return (float(np.sum(st.sums[_COST, sl], dtype=np.float64)), *_block_step(st, sl, fit=fit))


def _block_step(st: _State, sl: slice, *, fit: bool) -> tuple[float, ...]:
    """Damped Gauss–Newton step of a block's pixels (into ``st.delta0``, ``st.w``).

    Each pixel's 3x3 block H of J^T J is damped as H + lambda diag(H) (Marquardt) and
    inverted in closed form (adjugate, float32; :mod:`photometric.symmetric_solve`);
    delta0 = Hd^-1 J^T r, w = Hd^-1 J^T P, and the step for a change dA of A is
    delta0 - w dA. A (nearly) singular block gives a zero step and raises its pixel's
    damping.
    Returns the block's parts of the Schur complement on A: (P.r, (J^T P).delta0, P.P,
    (J^T P).w), or () if A is fixed.
    """
    s = st.sums[:, sl]
    lam = st.lam[sl]
    h11, h12, h13, h22, h23, h33 = s[_H11], s[_H12], s[_H13], s[_H22], s[_H23], s[_H33]
    tiny = (h11 + h22 + h33) * np.float32(1e-7) + np.float32(1e-30)
    d1 = h11 + lam * np.maximum(h11, tiny)
    d2 = h22 + lam * np.maximum(h22, tiny)
    d3 = h33 + lam * np.maximum(h33, tiny)
    a11, a12, a13, a22, a23, a33, det = symmetric_adjugate(d1, h12, h13, d2, h23, d3)
    ok = det > np.float32(1e-6) * d1 * d2 * d3
    inv_det = np.divide(np.float32(1.0), det, out=np.zeros_like(det), where=ok)
    if not ok.all():  # (nearly) singular: no step now, more damping next time
        lam[~ok] = np.minimum(lam[~ok] * np.float32(_LAMBDA_UP), np.float32(_LAMBDA_MAX))

    def solve(r1: np.ndarray, r2: np.ndarray, r3: np.ndarray, out: np.ndarray) -> np.ndarray:
        out[0], out[1], out[2] = adjugate_solve(a11, a12, a13, a22, a23, a33, inv_det, r1, r2,
                                                r3)
        return out

    delta0 = solve(s[_G1], s[_G2], s[_G3], st.delta0[:, sl])
    if not fit:
        return ()
    w = solve(s[_C1], s[_C2], s[_C3], st.w[:, sl])
    c = s[_C1:_C3 + 1]
    return (
        float(np.sum(s[_GA], dtype=np.float64)), float(np.sum(c * delta0, dtype=np.float64)),
        float(np.sum(s[_D], dtype=np.float64)), float(np.sum(c * w, dtype=np.float64)),
    )


def _block_candidate(
    ws: dict[str, np.ndarray], block: int, *, ev: _Evaluator, st: _State,
    scales: tuple[float, float], fit: bool,
) -> tuple[float, ...]:
    """The block's candidate (n, rho) for A -> ``scales[1]`` and its sums at that A.

    Returns the parts of the choice at that A (:func:`_block_choice`), or () if A is fixed.
    """
    sl = _block_slice(block)
    step = st.delta0[:, sl]
    d_scale = scales[1] - scales[0]
    if d_scale != 0.0:
        step = step - np.float32(d_scale) * st.w[:, sl]
    n = st.n[:, sl]
    t_x, t_y = _tangent_axes(n)
    st.n_new[:, sl] = _normalize(n + step[0] * t_x + step[1] * t_y)
    st.rho_new[sl] = np.maximum(st.rho[sl] + step[2], 0.0)
    ev.block_sums(ws, block, n=st.n_new, rho=st.rho_new, scale=scales[1], out=st.sums_new,
                  with_scale=fit)
    return _block_choice(ws, block, st=st, scales=scales, at=scales[1]) if fit else ()


def _choice_at(
    st: _State, sl: slice, scales: tuple[float, float], at: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of a block: cost of the current state and of the candidate at A = ``at``,
    and which is lower (accept the candidate).

    ``scales`` = (A at which ``st.sums`` were formed, A of ``st.sums_new``). The cost is
    quadratic in A: r -> r - dA P gives r.r - 2 dA P.r + dA^2 P.P.
    """
    costs = []
    for sums, a0 in ((st.sums, scales[0]), (st.sums_new, scales[1])):
        cost = sums[_COST, sl].astype(np.float64)
        delta = at - a0
        if delta != 0.0:
            cost += delta * (delta * sums[_D, sl] - 2.0 * sums[_GA, sl])
        costs.append(cost)
    return costs[0], costs[1], costs[1] <= costs[0]


def _block_choice(
    ws: dict[str, np.ndarray], block: int, *, st: _State, scales: tuple[float, float],
    at: float,
) -> tuple[float, float, float]:
    """For the choice at A = ``at``: the block's parts of the chosen cost, of P.r and of
    P.P (for the closed-form A)."""
    sl = _block_slice(block)
    old, new, accept = _choice_at(st, sl, scales, at)
    g_a = np.where(
        accept, st.sums_new[_GA, sl] - (at - scales[1]) * st.sums_new[_D, sl],
        st.sums[_GA, sl] - (at - scales[0]) * st.sums[_D, sl],
    )
    d = np.where(accept, st.sums_new[_D, sl], st.sums[_D, sl])
    return float(np.sum(np.where(accept, new, old))), float(np.sum(g_a)), float(np.sum(d))


def _shift_rows(sums: np.ndarray, delta: float) -> None:
    """In place: the sums (15, B) after A -> A + delta (n, rho unchanged; J kept)."""
    if delta == 0.0:
        return
    sums[_COST] += delta * (delta * sums[_D] - 2.0 * sums[_GA])
    sums[_G1] -= delta * sums[_C1]
    sums[_G2] -= delta * sums[_C2]
    sums[_G3] -= delta * sums[_C3]
    sums[_GA] -= delta * sums[_D]


def _block_commit(
    ws: dict[str, np.ndarray], block: int, *, st: _State, scales: tuple[float, float],
    at: float, fit: bool,
) -> tuple[float, ...]:
    """Take the chosen states of a block at A = ``at``, bring their sums to that A, adapt
    the damping, and take the next step. Returns (the block's new cost, the Schur parts of
    :func:`_block_step`)."""
    sl = _block_slice(block)
    old_cost, new_cost, accept = _choice_at(st, sl, scales, at)
    old, new = st.sums[:, sl], st.sums_new[:, sl]
    _shift_rows(old, at - scales[0])
    _shift_rows(new, at - scales[1])
    pairs = ((old, new), (st.n[:, sl], st.n_new[:, sl]), (st.rho[sl], st.rho_new[sl]))
    if np.all(np.isfinite(new_cost)):
        # cur += accept (cand - cur): masked copies are slow on irregular masks.
        for cur, cand in pairs:
            cand -= cur
            cand *= accept
            cur += cand
    else:  # a non-finite candidate must not leak through 0 * NaN
        for cur, cand in pairs:
            np.copyto(cur, cand, where=accept)
    lam = st.lam[sl]
    lam *= np.where(accept, np.float32(_LAMBDA_DOWN), np.float32(_LAMBDA_UP))
    np.clip(lam, np.float32(_LAMBDA_MIN), np.float32(_LAMBDA_MAX), out=lam)
    cost = float(np.sum(np.where(accept, new_cost, old_cost)))
    return (cost, *_block_step(st, sl, fit=fit))


def _determined(sums: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 J^T J (sums (15, N)) is non-singular: their solution is determined
    (not, e.g., every usable light in attached shadow at the normal found)."""
    h11, h12, h13, h22, h23, h33 = (sums[i] for i in (_H11, _H12, _H13, _H22, _H23, _H33))
    det = symmetric_adjugate(h11, h12, h13, h22, h23, h33)[6]
    return det > 1e-9 * h11 * h22 * h33


def _block_slice(block: int) -> slice:
    return slice(block * _BLOCK, (block + 1) * _BLOCK)


class _Evaluator:
    """Per-pixel sums of the model over blocks of pixels, in worker threads.

    Each worker owns a workspace of (K, B) float32 buffers reused from block to block and
    from call to call, so the heavy arithmetic runs in cache and allocates nothing large.
    Use as a context manager (the thread pool is shut down on exit).
    """

    _BUFFERS = (
        "ci", "tmp", "g", "em", "inv_ci", "q", "x", "e", "att", "p", "c", "r", "dd", "gq",
        "dfi", "dfr", "j1", "j2", "dinv",
    )

    def __init__(self, data: _Data) -> None:
        self.data = data
        k = data.values.shape[1]
        self.workers = max(1, min(thread_limit(), data.blocks))
        self._spaces = [
            {name: np.empty((k, _BLOCK), np.float32) for name in self._BUFFERS}
            | {"lit": np.empty((k, _BLOCK), bool)}
            for _ in range(self.workers)
        ]
        self._pool = ThreadPoolExecutor(self.workers) if self.workers > 1 else None

    def __enter__(self) -> _Evaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def map(self, job: Callable[[dict[str, np.ndarray], int], _T]) -> list[_T]:
        """``job(workspace, block)`` for every block (blocks dealt out to the workers);
        the results in block order, so that sums do not depend on the number of threads."""
        def worker(index: int) -> list[_T]:
            space = self._spaces[index]
            return [job(space, b) for b in range(index, self.data.blocks, self.workers)]

        if self._pool is None:
            return worker(0)
        futures = [self._pool.submit(worker, i) for i in range(self.workers)]
        results: list[_T] = [None] * self.data.blocks  # type: ignore[list-item]
        for index, future in enumerate(futures):
            results[index::self.workers] = future.result()
        return results

    def block_sums(
        self, ws: dict[str, np.ndarray], block: int, *, n: np.ndarray, rho: np.ndarray,
        scale: float, out: np.ndarray, with_scale: bool,
    ) -> None:
        """The per-pixel sums of one block into ``out[:, block slice]`` (float32 (15, Np)).

        Rows (index constants ``_H11`` ...): J^T J (upper triangle, unknowns (a, b, rho)),
        J^T r, then J^T P, P.P and P.r (only ``with_scale``; else left as they are) and r.r,
        where r = I - f over the usable measurements, P = df/dA, and (a, b) the step along
        the tangent directions of :func:`_tangent_axes` at n.
        """
        sl = _block_slice(block)
        terms = self._jacobian(ws, block, n[:, sl], rho[sl], np.float32(scale))
        rows = out[:, sl]
        for row, a, b in _ROWS_WITH_SCALE if with_scale else _ROWS:
            np.einsum("kn,kn->n", terms[a], terms[b], out=rows[row])

    def block_values(
        self, ws: dict[str, np.ndarray], block: int, n32: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """P (= e p S) and C (= e c_i) of one block, zero where not lit or not usable."""
        d = self.data
        ci, lit = ws["ci"], ws["lit"]
        self._light_dot(block, n32, ci, ws["tmp"])
        cr = _dot3(self._views(block), n32)
        np.greater(ci, 0, out=lit)
        np.logical_and(lit, d.usable[block], out=lit)
        if np.any(cr <= 0):
            lit &= cr > 0
        phase = d.phase if d.phase.shape[1] == 1 else d.phase[block]
        g = np.multiply(phase, lit, out=ws["g"])  # e p where lit and usable, else 0
        intensity = d.intensity if d.intensity.shape[1] == 1 else d.intensity[block]
        em = np.multiply(intensity, lit, out=ws["em"])  # e where lit and usable, else 0
        np.maximum(ci, np.float32(_VALUE_FLOOR), out=ci)
        np.maximum(cr, np.float32(_VALUE_FLOOR), out=cr)
        ws["cr"] = cr
        inv_ci = np.divide(np.float32(1.0), ci, out=ws["inv_ci"])
        q = np.add(ci, cr, out=ws["q"])
        np.divide(ci, q, out=q)  # c_i / (c_i + c_r)
        x = np.add(inv_ci, np.float32(1.0) / cr, out=ws["x"])
        x *= np.float32(-d.tau)
        big_e = cv2.exp(x, ws["e"])  # exp(-tau (1/c_i + 1/c_r))
        att = np.subtract(np.float32(1.0), big_e, out=ws["att"])
        p = np.multiply(att, q, out=ws["p"])
        p *= g  # e p S
        c = np.multiply(ci, em, out=ws["c"])  # e c_i
        return p, c

    def _light_dot(self, block: int, vec: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
        """out = l_k . vec for every light and pixel of the block (vec (3, B) float32)."""
        if self.data.per_pixel_lights:
            lgt = self.data.lights[block]
            np.multiply(lgt[0], vec[0], out=out)
            out += np.multiply(lgt[1], vec[1], out=tmp)
            out += np.multiply(lgt[2], vec[2], out=tmp)
        else:
            np.einsum("kc,cn->kn", self.data.lights, vec, out=out)

    def _views(self, block: int) -> np.ndarray:
        v = self.data.views
        return v if v.shape[1] == 1 else v[:, _block_slice(block)]

    def _jacobian(
        self, ws: dict[str, np.ndarray], block: int, n32: np.ndarray, rho32: np.ndarray,
        scale: np.float32,
    ) -> dict[str, np.ndarray]:
        """Residual r, P, C and the Jacobian columns j1, j2 (tangent steps) of one block.

        f = A P + rho C. With D = (1 - E)(1 - q) the derivatives of S = q (1 - E) are
        dS/dc_i = (q / c_i)(D - tau E / c_i) and dS/dc_r = -(q / c_r)(D + tau E / c_r),
        and df/dn . t = df/dc_i (l . t) + df/dc_r (v . t), where for the tangent directions
        t_x = e_x - n_x n, t_y = e_y - n_y n (:func:`_tangent_axes`) l . t_x = l_x - c_i n_x
        (no dot product needed). The factors 1/c_i and 1/c_r of
        the derivatives are capped at 1 / ``_DERIVATIVE_FLOOR`` (q, 1 - q <= 1 already), so
        they stay finite where c_i or c_r -> 0.
        """
        d = self.data
        p, c = self.block_values(ws, block, n32)
        cr, tmp, q = ws["cr"], ws["tmp"], ws["q"]
        pa = np.multiply(p, scale, out=ws["r"])  # A P, the single-scattering term
        u = np.subtract(np.float32(1.0), q, out=ws["dd"])
        u *= pa  # A e p q (1 - q)(1 - E)
        r = np.subtract(d.values[block], pa, out=pa)
        r -= np.multiply(c, rho32, out=tmp)  # r = I - A P - rho C
        # wq = A e p q tau E (E is overwritten)
        wq = np.multiply(ws["g"], q, out=ws["gq"])
        wq *= ws["e"]
        wq *= np.float32(scale * d.tau)
        d_inv_cr = np.float32(1.0) / np.maximum(cr, np.float32(_DERIVATIVE_FLOOR))
        d_inv_ci = np.minimum(ws["inv_ci"], np.float32(1.0 / _DERIVATIVE_FLOOR), out=ws["dinv"])
        dfr = np.multiply(wq, d_inv_cr, out=ws["dfr"])
        dfr += u
        dfr *= d_inv_cr  # -df/dc_r = (A e p q / c_r)(D + tau E / c_r)
        dfi = np.multiply(wq, d_inv_ci, out=ws["dfi"])
        np.subtract(u, dfi, out=dfi)
        dfi *= d_inv_ci
        dfi += np.multiply(ws["em"], rho32, out=tmp)  # df/dc_i = A e p dS/dc_i + rho e
        views = self._views(block)
        ci = ws["ci"]
        j1, j2 = ws["j1"], ws["j2"]
        for axis, j in ((0, j1), (1, j2)):
            n_axis = n32[axis]
            np.multiply(ci, n_axis, out=j)
            lgt = d.lights[block][axis] if d.per_pixel_lights else d.lights[:, axis:axis + 1]
            np.subtract(lgt, j, out=j)  # l . t = l_axis - c_i n_axis
            j *= dfi
            j -= np.multiply(dfr, views[axis] - cr * n_axis, out=tmp)  # v . t likewise
        return {"j1": j1, "j2": j2, "c": c, "p": p, "r": r}


# (row, term, term) of each per-pixel sum of _Evaluator.block_sums.
_ROWS = (
    (_H11, "j1", "j1"), (_H12, "j1", "j2"), (_H13, "j1", "c"), (_H22, "j2", "j2"),
    (_H23, "j2", "c"), (_H33, "c", "c"), (_G1, "j1", "r"), (_G2, "j2", "r"), (_G3, "c", "r"),
    (_COST, "r", "r"),
)
_ROWS_WITH_SCALE = (
    *_ROWS, (_C1, "j1", "p"), (_C2, "j2", "p"), (_C3, "c", "p"), (_D, "p", "p"),
    (_GA, "p", "r"),
)


def _check(
    images: np.ndarray,
    lights: np.ndarray,
    *,
    mask: np.ndarray,
    init_normals: np.ndarray,
    init_albedo: np.ndarray,
    views: np.ndarray | tuple[float, float, float],
    intensities: np.ndarray | None,
    usable: np.ndarray | None,
    params: SkinParams,
) -> _Inputs:
    """Check the inputs (FingerpsReconError on bad ones); nothing large is converted."""
    imgs = np.asarray(images)
    if imgs.ndim != 3 or not (
        np.issubdtype(imgs.dtype, np.integer) or np.issubdtype(imgs.dtype, np.floating)
    ):
        raise FingerpsReconError(
            f"images must be a real (K, H, W) array, got shape {imgs.shape} dtype {imgs.dtype}"
        )
    k, h, w = imgs.shape
    if k < 3:
        raise FingerpsReconError(f"photometric stereo needs at least 3 lights, got {k}")
    lgt = np.asarray(lights)
    if lgt.shape == (k, 3):
        per_pixel = False
    elif lgt.shape == (k, h, w, 3):
        per_pixel = True
    else:
        raise FingerpsReconError(
            f"lights must have shape (K, 3) = ({k}, 3) or (K, H, W, 3) = ({k}, {h}, {w}, 3) "
            f"to match images {imgs.shape}, got {lgt.shape}"
        )
    if not isinstance(params, SkinParams):
        raise FingerpsReconError(f"params must be a SkinParams, got {type(params).__name__}")
    m = np.asarray(mask)
    if m.shape != (h, w) or m.dtype != bool:
        raise FingerpsReconError(
            f"mask must be a bool array of shape (H, W) = ({h}, {w}), got {m.shape} {m.dtype}"
        )
    n_in = np.asarray(init_normals)
    if n_in.shape != (h, w, 3):
        raise FingerpsReconError(
            f"init_normals must have shape (H, W, 3) = ({h}, {w}, 3), got {n_in.shape}"
        )
    rho_in = np.asarray(init_albedo)
    if rho_in.shape != (h, w):
        raise FingerpsReconError(
            f"init_albedo must have shape (H, W) = ({h}, {w}), got {rho_in.shape}"
        )
    vw = np.asarray(views)
    if vw.shape not in ((3,), (h, w, 3)):
        raise FingerpsReconError(
            f"views must have shape (3,) or (H, W, 3) = ({h}, {w}, 3), got {vw.shape}"
        )
    e = checked_intensities(intensities, shape=(k, h, w))
    use_in = None
    if usable is not None:
        use_in = np.asarray(usable)
        if use_in.shape != (k, h, w) or use_in.dtype != bool:
            raise FingerpsReconError(
                f"usable must be a bool array of shape (K, H, W) = ({k}, {h}, {w}), got "
                f"{use_in.shape} {use_in.dtype}"
            )
    if not per_pixel:
        lgt = _unit_or_raise(lgt.astype(np.float64), "lights")
    if vw.ndim == 1:
        vw = _unit_or_raise(vw.astype(np.float64), "views")

    return _Inputs(
        images=imgs, lights=lgt, per_pixel_lights=per_pixel, mask=m, normals=n_in,
        albedo=rho_in, views=vw, intensities=e, usable=use_in, params=params,
    )


@dataclass(frozen=True)
class _Inputs:
    """solve_hk's inputs, checked (:func:`_check`): as given, except distant lights (K, 3)
    and a single view (3,) normalised (float64) and intensities (K,) as float64; ``usable``
    None for the default (finite and > 0)."""

    images: np.ndarray  # (K, H, W)
    lights: np.ndarray  # (K, 3) or (K, H, W, 3)
    per_pixel_lights: bool
    mask: np.ndarray  # (H, W) bool
    normals: np.ndarray  # (H, W, 3)
    albedo: np.ndarray  # (H, W)
    views: np.ndarray  # (3,) or (H, W, 3)
    intensities: np.ndarray  # (K,) or (K, H, W)
    usable: np.ndarray | None  # (K, H, W) bool
    params: SkinParams


def _prepare(inputs: _Inputs) -> tuple[_Columns, np.ndarray, tuple[int, int]]:
    """The valid pixels' data (numpy backend): (their columns, their flat indices (N,),
    (H, W)). Only the masked pixels of the inputs are converted."""
    imgs, lgt, per_pixel, m = inputs.images, inputs.lights, inputs.per_pixel_lights, inputs.mask
    n_in, rho_in, vw, e = inputs.normals, inputs.albedo, inputs.views, inputs.intensities
    use_in, params = inputs.usable, inputs.params
    k, h, w = imgs.shape

    # Candidate pixels: in the mask, with a usable initial normal and albedo.
    # (np.take gathers much faster than fancy indexing.)
    cand = np.flatnonzero(m)
    n_c = np.take(n_in.reshape(h * w, 3), cand, axis=0).astype(np.float64)
    rho_c = np.take(rho_in.reshape(h * w), cand).astype(np.float64)
    norm = np.sqrt(np.einsum("nc,nc->n", n_c, n_c))
    with np.errstate(invalid="ignore"):
        good = np.isfinite(norm) & (norm > 0) & np.isfinite(rho_c)
    values = np.take(imgs.reshape(k, h * w), cand, axis=1).astype(np.float32, copy=False)
    with np.errstate(invalid="ignore"):
        use = values > 0 if use_in is None else np.take(use_in.reshape(k, h * w), cand, axis=1)
        if np.issubdtype(imgs.dtype, np.floating):
            use &= np.isfinite(values)
    if e.ndim == 3:  # per-pixel intensities: not finite or <= 0 -> measurement left out
        e_c = np.take(e.reshape(k, h * w), cand, axis=1).astype(np.float32)
        with np.errstate(invalid="ignore"):
            use &= np.isfinite(e_c) & (e_c > 0)
    counts = np.add.reduce(use.view(np.uint8), axis=0, dtype=np.int32)
    keep = good & (counts >= 3)
    n0, rho0 = n_c.T / norm, rho_c  # (3, N), (N,)
    if not keep.all():
        kept = np.flatnonzero(keep)
        cand, counts, rho0 = cand[kept], counts[kept], rho0[kept]
        values, use, n0 = (np.take(a, kept, axis=1) for a in (values, use, n0))
        if e.ndim == 3:
            e_c = np.take(e_c, kept, axis=1)
    pix = cand

    # Directions component-major: lights (3, K, N) or (3, K, 1), views (3, N) or (3, 1).
    if per_pixel:
        l_dirs = _unit_columns(
            np.moveaxis(np.take(lgt.reshape(k, h * w, 3), pix, axis=1), -1, 0), "lights"
        )
    else:
        l_dirs = lgt.T[:, :, None].astype(np.float32)
    if vw.ndim == 3:
        v_cols = _unit_columns(np.take(vw.reshape(h * w, 3), pix, axis=0).T, "views")
    else:
        v_cols = vw[:, None].astype(np.float32)

    # Phase function of each measurement (depends on l and v only): computed once.
    c_phi = _dot3(l_dirs, v_cols[:, None, :])
    c_sc = -c_phi if params.phase is PhaseConvention.PHYSICAL else c_phi
    if e.ndim == 3:
        intensity = np.where(use, e_c, np.float32(1.0))  # (K, N)
    else:
        intensity = e.astype(np.float32)[:, None]  # (K, 1)
    phase = intensity * henyey_greenstein(np.clip(c_sc, -1, 1), params.g)

    # Initial normals, tilted towards the camera where they face away from it.
    c_r = _dot3(v_cols, n0)
    low = c_r < _MIN_INIT_CR
    if np.any(low):
        v_low = np.broadcast_to(v_cols, n0.shape)[:, low]
        n0[:, low] = _normalize(n0[:, low] + (_MIN_INIT_CR - c_r[low]) * v_low)

    values[~use] = 0.0
    columns = _Columns(
        values=values, usable=use, counts=counts.astype(np.float64),
        lights=l_dirs if per_pixel else lgt.astype(np.float32),
        per_pixel_lights=per_pixel, views=v_cols,
        intensity=intensity, phase=phase,
        tau=float(params.optical_depth), normals=n0, albedo=rho0,
    )
    return columns, pix, (h, w)


@dataclass(frozen=True)
class _Columns:
    """The valid pixels' data, one column per pixel, before packing into blocks.

    ``values``, ``usable`` (K, N); ``lights`` (3, K, N) per pixel or (K, 3); ``views``
    (3, N) or (3, 1); ``phase`` (K, N) or (K, 1); ``normals`` (3, N); ``albedo`` (N,).
    """

    values: np.ndarray
    usable: np.ndarray
    counts: np.ndarray
    lights: np.ndarray
    per_pixel_lights: bool
    views: np.ndarray
    intensity: np.ndarray
    phase: np.ndarray
    tau: float
    normals: np.ndarray
    albedo: np.ndarray

    def pack(self, select: slice = slice(None)) -> tuple[_Data, np.ndarray, np.ndarray]:
        """The pixels ``select`` by block (padding pixels have no usable measurement):
        (data, initial normals (3, N_padded), initial albedo (N_padded,))."""
        count = self.albedo[select].size
        blocks = max(1, -(-count // _BLOCK))
        padded = blocks * _BLOCK

        def by_block(a: np.ndarray, fill: float | bool) -> np.ndarray:
            """(..., N) -> (blocks, ..., B), padded with ``fill``."""
            cols = a[..., select]
            out = np.empty((blocks, *a.shape[:-1], _BLOCK), dtype=a.dtype)
            for b in range(blocks):
                part = cols[..., b * _BLOCK:(b + 1) * _BLOCK]
                out[b, ..., : part.shape[-1]] = part
            out[-1, ..., count - (blocks - 1) * _BLOCK:] = fill
            return out

        n_pad = np.zeros((3, padded))
        n_pad[2] = 1.0
        n_pad[:, :count] = self.normals[:, select]
        rho_pad = np.zeros(padded)
        rho_pad[:count] = self.albedo[select]
        data = _Data(
            values=by_block(self.values, 0.0),
            usable=by_block(self.usable, False),
            counts=self.counts[select],
            lights=by_block(self.lights, 0.0) if self.per_pixel_lights else self.lights,
            per_pixel_lights=self.per_pixel_lights,
            views=(
                self.views if self.views.shape[1] == 1
                else _pad_columns(self.views[:, select], padded)
            ),
            intensity=(
                self.intensity if self.intensity.shape[1] == 1
                else by_block(self.intensity, 1.0)
            ),
            phase=self.phase if self.phase.shape[1] == 1 else by_block(self.phase, 0.0),
            tau=self.tau,
        )
        return data, n_pad, rho_pad


def _pad_columns(a: np.ndarray, width: int) -> np.ndarray:
    """(3, N) -> (3, width) padded with (0, 0, 1) columns."""
    out = np.zeros((3, width), dtype=a.dtype)
    out[2] = 1.0
    out[:, : a.shape[1]] = a
    return out


def _unit_or_raise(v: np.ndarray, name: str) -> np.ndarray:
    """``v`` (..., 3) normalised; FingerpsReconError if any vector is non-finite or zero."""
    if not np.all(np.isfinite(v)):
        raise FingerpsReconError(f"{name} contain non-finite values; check the calibration")
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise FingerpsReconError(f"{name} contain zero vectors; give unit directions")
    return v / norm


def _unit_columns(v: np.ndarray, name: str) -> np.ndarray:
    """``v`` (3, ...) normalised along the first axis, as float32; FingerpsReconError if any
    vector is non-finite or zero."""
    out = v.astype(np.float32)
    norm = np.sqrt(_dot3(out, out))
    if not np.all(np.isfinite(norm)):
        raise FingerpsReconError(
            f"{name} contain non-finite values inside the mask; check the calibration"
        )
    if np.any(norm == 0):
        raise FingerpsReconError(f"{name} contain zero vectors inside the mask")
    out /= norm
    return out


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Column-wise dot product of (3, N) or (3, 1) with (3, N) -> (N,)."""
    out = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


def _normalize(v: np.ndarray) -> np.ndarray:
    """Columns of (3, N) scaled to unit length."""
    return v / np.sqrt(np.sum(v * v, axis=0))


def _tangent_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent directions t_x = e_x - n_x n and t_y = e_y - n_y n of unit normals (3, N).

    The projections of the x and y axes onto the tangent plane: a basis of it wherever
    n_z != 0 (the determinant of their Gram matrix is n_z^2), i.e. for every normal that is
    not perpendicular to the camera axis. Used for the step n <- normalize(n + a t_x + b t_y).
    """
    nx, ny = n[0], n[1]
    t_x = -nx * n
    t_x[0] += 1.0
    t_y = -ny * n
    t_y[1] += 1.0
    return t_x, t_y
