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

A held (``scale`` given, e.g. the A a previous burst of the same rig refitted: A depends on
the skin and the LEDs' power, not on the pose). The pixels are then independent: one
compiled pass gathers, solves and writes out each chunk of pixels while it stays in the
core's cache (``hk_passes_kernel.solve_held``), with the same steps (rho in closed form for the
held A, then Levenberg–Marquardt, each pixel keeping the better of its state and its
candidate); a chunk stops once the decrease its next steps promise (the Gauss–Newton
model's, at least (J^T r) . delta) is at most ``tol`` times its cost, so no iteration is
evaluated only to find that it gained nothing. ``HKResult.refit_scale`` is A's linear fit
with every rho at the solution's normals: holding each burst at the previous burst's refit
is block-coordinate descent across bursts, whose fixed point is the joint minimum (the
pixels' gradients vanish at their solution, A's at its linear fit).

The derivatives dS/dc_i and dS/dc_r of S = c_i / (c_i + c_r) (1 - E) contain 1/c_i and 1/c_r
and blow up as c_i or c_r -> 0; those factors are capped at 1 / ``DERIVATIVE_FLOOR`` (the
model values are not changed), so the Jacobian stays finite. The optical-depth exponential
E = exp(-tau_d (1/c_i + 1/c_r)) is evaluated exactly: for the finger constants it is below
3e-4 at every angle (tau_d (1/c_i + 1/c_r) >= 2 tau_d = 8.3, never above the 30 at which it
could be dropped), small but not negligible at float32 precision.

Arithmetic. The per-pixel passes are compiled (numba: :mod:`photometric.hk_model_kernel`
the model and its layout, ``hk_gather_kernel``, ``hk_step_kernel``,
``hk_passes_kernel``): each pass one loop over chunks of pixels, vectorised, in up to
:func:`fingerps_recon.photometric.kernel_threads.thread_limit` numba threads; the
per-measurement work in float32, the per-pixel sums and state float32, A and the totals
float64. float32 limits how closely a pixel's minimum is approached: its cost stays within
about 1e-6 (relative) of the float64 optimum (``tests/core/test_hk_solver.py`` checks the
minimum against scipy's ``least_squares`` per pixel). The first call in a process compiles
the kernels or loads them from numba's on-disk cache
(:mod:`fingerps_recon.photometric.kernel_warm_up`).
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, fields
from types import ModuleType

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.hk_inputs import (
    check_burst,
    check_images,
    check_lighting,
    check_options,
    checked_mask,
)
from fingerps_recon.photometric.hk_joint_fit import JointPasses, fit_jointly
from fingerps_recon.photometric.hk_model import PhaseConvention, SkinParams
from fingerps_recon.photometric.hk_settings import LAMBDA_START, MIN_INIT_CR, kernel_consts
from fingerps_recon.photometric.kernel_threads import numba_threads


@dataclass(frozen=True)
class _Kernels:
    """The modules of the compiled kernels (numba), ``photometric.hk_<field>_kernel``."""

    model: ModuleType  # the model and the passes' layout (chunk size, rows, flags)
    gather: ModuleType  # the lighting of a calibration, a burst's pixels gathered
    passes: ModuleType  # the passes: the solve with A held, the fit with A fitted jointly


# The compiled kernels, imported once per process: [_Kernels] or [None, reason] if numba
# cannot be set up.
_KERNELS: list = []


def _kernels() -> _Kernels:
    """The compiled kernels' modules, or FingerpsReconError saying why numba is missing."""
    if not _KERNELS:
        try:
            _KERNELS.append(_Kernels(**{
                field.name: importlib.import_module(f"{__package__}.hk_{field.name}_kernel")
                for field in fields(_Kernels)}))
        except Exception as exc:  # ImportError, or numba failing to set itself up
            _KERNELS.extend([None, f"{type(exc).__name__}: {exc}"])
    if _KERNELS[0] is None:
        raise FingerpsReconError(
            f"the HK solver's compiled kernels cannot be imported ({_KERNELS[1]}); install "
            "numba and llvmlite (requirements.txt)")
    return _KERNELS[0]


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
        initialisation and after each iteration; non-increasing. With A held (``scale``
        given), after the initialisation and at the end (each chunk of pixels iterates on
        its own; ``iterations`` is the most any chunk did).
    refit_scale : float
        A's linear least-squares fit (with every rho) at the solution's normals: with A
        fitted, ``scale`` itself; with A held, where the next burst of the same rig should
        hold it (NaN if no pixel was valid).
    mean_iterations : float
        The iterations done, averaged over the chunks of pixels: with A fitted,
        ``iterations``; with A held, less where chunks stopped early (the work done, e.g.
        for a rate per iteration). NaN if no pixel was valid.
    """

    normals: np.ndarray
    albedo: np.ndarray
    scale: float
    valid: np.ndarray
    residual_rms: np.ndarray
    iterations: int
    cost_history: tuple[float, ...]
    refit_scale: float = float("nan")
    mean_iterations: float = float("nan")


@dataclass(frozen=True)
class HKLighting:
    """The lighting of one calibration in the HK passes' layout (:func:`prepare_hk_lighting`):
    what :func:`solve_hk_prepared` needs that does not change from burst to burst.

    Attributes
    ----------
    shape : (H, W)
        Image size.
    light_count : int
        K.
    params : SkinParams
        The skin model (phase function, optical depth).
    index : (H*W,) int64
        Each image pixel's column in ``terms``, -1 where it was not prepared (outside the
        mask it was prepared for).
    terms, views, bad : arrays
        Light directions, e p and e; view directions; bad-direction flags
        (:func:`photometric.hk_gather_kernel.lighting_terms`).
    """

    shape: tuple[int, int]
    light_count: int
    params: SkinParams
    index: np.ndarray
    terms: np.ndarray
    views: np.ndarray
    bad: np.ndarray


def prepare_hk_lighting(
    lights: np.ndarray,
    *,
    shape: tuple[int, int],
    views: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
    intensities: np.ndarray | None = None,
    params: SkinParams = SkinParams(),  # noqa: B008 (frozen dataclass)
    mask: np.ndarray | None = None,
) -> HKLighting:
    """The lighting of a calibration for :func:`solve_hk_prepared` (parameters as
    :func:`solve_hk`), for every pixel of ``shape`` or, with ``mask`` (H, W) bool, for its
    pixels. Computed once per calibration and camera; raises ``FingerpsReconError`` on
    inconsistent shapes or bad directions."""
    h, w = (int(v) for v in shape)
    lgt, per_pixel, vw, e = check_lighting(lights, (h, w), views, intensities, params)
    kernels = _kernels()
    k = lgt.shape[0]
    hw = h * w
    if mask is None:
        pixels = np.arange(hw, dtype=np.int64)
    else:
        pixels = np.flatnonzero(checked_mask(mask, (h, w))).astype(np.int64)
    index = np.full(hw, -1, np.int64)
    index[pixels] = np.arange(pixels.size)
    f32 = np.float32
    g = f32(params.g)
    hg = np.array([1 + g * g, 2 * g, 1 - g * g, f32(4 * math.pi)], f32)
    terms = np.empty((k, kernels.model.N_TERMS, pixels.size), f32)
    v_out = np.empty((3, pixels.size), f32)
    bad = np.empty(pixels.size, np.uint8)
    kernels.gather.lighting_terms(
        pixels, _float_array(lgt, (k, hw, 3) if per_pixel else (k, 1, 3)),
        _float_array(vw, (hw, 3) if vw.ndim == 3 else (1, 3)),
        _float_array(e, (k, hw) if e.ndim == 3 else (k, 1)), hg,
        params.phase is PhaseConvention.PHYSICAL, terms, v_out, bad)
    return HKLighting(shape=(h, w), light_count=k, params=params, index=index, terms=terms,
                      views=v_out, bad=bad)


def prepare_hk_lighting_at_depth(
    lighting: HKLighting,
    depth_m: np.ndarray,
    *,
    mask: np.ndarray,
    led_positions_optical: np.ndarray,
    plane_power: np.ndarray | None,
    working_distance_m: float,
) -> HKLighting:
    """The near lights of ``lighting`` (prepared for the plane z = ``working_distance_m``,
    :func:`photometric.pixel_rays.near_light_directions_ps`, with perspective views) moved
    to the surface points of a depth map, for the pixels of ``mask``: per pixel the
    direction from the point at ``depth_m`` (H, W) (optical z, metres; the plane's point
    where it is not finite) on the pixel's ray (minus its view) towards each LED
    ``led_positions_optical`` (K, 3) (metres, optical frame),
    and ``plane_power`` (K, H, W) or (K,) (the irradiance on the plane, e.g. the white
    target's; None: all ones) moved there by the inverse-square law
    (:func:`photometric.hk_gather_kernel.near_lighting_terms`). The views and the skin
    constants are ``lighting``'s. One compiled pass over the mask's pixels: cheap enough
    per burst, for a second solve once the depth is known."""
    h, w = lighting.shape
    k = lighting.light_count
    leds = np.ascontiguousarray(led_positions_optical, dtype=np.float64)
    if leds.shape != (k, 3) or not np.isfinite(leds).all():
        raise FingerpsReconError(
            f"LED positions must be {k} finite points (K, 3), got shape {leds.shape}")
    if np.shape(depth_m) != (h, w):
        raise FingerpsReconError(f"depth {np.shape(depth_m)} does not fit the lighting's "
                                 f"{w} x {h} px")
    if plane_power is None:
        power = np.ones((k, 1), np.float32)
    else:
        power = np.asarray(plane_power, dtype=np.float32)
        if power.shape not in ((k,), (k, h, w)):
            raise FingerpsReconError(f"irradiance {power.shape} fits neither ({k},) nor "
                                     f"({k}, {h}, {w})")
        power = np.ascontiguousarray(power.reshape(k, -1))
    pixels = np.flatnonzero(checked_mask(mask, (h, w))).astype(np.int64)
    if np.any(lighting.index[pixels] < 0):
        raise FingerpsReconError(
            "the mask holds pixels the lighting was not prepared for: prepare it for the "
            "whole image (prepare_hk_lighting without a mask)")
    index = np.full(h * w, -1, np.int64)
    index[pixels] = np.arange(pixels.size)
    kernels = _kernels()
    f32 = np.float32
    g = f32(lighting.params.g)
    hg = np.array([1 + g * g, 2 * g, 1 - g * g, f32(4 * math.pi)], f32)
    terms = np.empty((k, kernels.model.N_TERMS, pixels.size), f32)
    v_out = np.empty((3, pixels.size), f32)
    bad = np.empty(pixels.size, np.uint8)
    with numba_threads():
        kernels.gather.near_lighting_terms(
            pixels, _float_array(depth_m, (h * w,)), leds, power, float(working_distance_m),
            lighting.views, lighting.index, hg,
            lighting.params.phase is PhaseConvention.PHYSICAL, terms, v_out, bad)
    return HKLighting(shape=(h, w), light_count=k, params=lighting.params, index=index,
                      terms=terms, views=v_out, bad=bad)


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
) -> HKResult:
    """Normals, albedo and the global scale A under the simplified HK model (Eq. 6-7).

    See the module docstring for the model and the method. The phase function's
    scattering-angle convention is ``params.phase`` (``PhaseConvention.PHYSICAL`` by
    default: c = -l.v). :func:`prepare_hk_lighting` for the mask's pixels, then
    :func:`solve_hk_prepared` (a stream of bursts with one calibration should prepare the
    lighting once).

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
    Returns
    -------
    HKResult

    Raises
    ------
    FingerpsReconError
        On inconsistent shapes, fewer than 3 lights, non-finite or zero light directions,
        non-positive intensities, bad options, or numba missing. The inputs are not
        modified.
    """
    imgs = check_images(images)
    k, h, w = imgs.shape
    if np.shape(lights) not in ((k, 3), (k, h, w, 3)):
        raise FingerpsReconError(
            f"lights must have shape (K, 3) = ({k}, 3) or (K, H, W, 3) = ({k}, {h}, {w}, 3) "
            f"to match images {imgs.shape}, got {np.shape(lights)}"
        )
    check_options(scale, iterations, tol)
    lighting = prepare_hk_lighting(lights, shape=imgs.shape[1:], views=views,
                                   intensities=intensities, params=params,
                                   mask=checked_mask(mask, imgs.shape[1:]))
    return solve_hk_prepared(imgs, lighting, mask=mask, init_normals=init_normals,
                             init_albedo=init_albedo, usable=usable, scale=scale,
                             iterations=iterations, tol=tol)


def solve_hk_prepared(
    images: np.ndarray,
    lighting: HKLighting,
    *,
    mask: np.ndarray,
    init_normals: np.ndarray,
    init_albedo: np.ndarray,
    usable: np.ndarray | None = None,
    scale: float | None = None,
    initial_scale: float | None = None,
    iterations: int = 10,
    tol: float = 1e-6,
) -> HKResult:
    """:func:`solve_hk` with the lighting prepared by :func:`prepare_hk_lighting` (the other
    parameters as there). ``initial_scale``: where the fit of A starts (``scale`` None),
    e.g. the A of the previous burst of the same rig, which saves the iterations A needs
    to get there from the global linear fit (None: that fit). Raises
    ``FingerpsReconError`` on inputs that do not fit the lighting (size, light count, a
    mask pixel whose chunk was not prepared)."""
    kernels = _kernels()
    imgs = check_images(images)
    check_options(scale, iterations, tol)
    if initial_scale is not None:
        check_options(initial_scale, iterations, tol)
    k, h, w = imgs.shape
    if (h, w) != lighting.shape or k != lighting.light_count:
        raise FingerpsReconError(
            f"images {imgs.shape} do not fit the prepared lighting of {lighting.light_count} "
            f"lights and {lighting.shape[1]} x {lighting.shape[0]} px")
    m, n_in, rho_in, use_in = check_burst(imgs.shape, mask, init_normals, init_albedo, usable)
    cand = np.flatnonzero(m)
    if np.any(lighting.index[cand] < 0):
        raise FingerpsReconError(
            "the mask holds pixels the lighting was not prepared for: prepare it for the "
            "whole image (prepare_hk_lighting without a mask)")
    fit, iterations, tol = scale is None, int(iterations), float(tol)
    with numba_threads():
        return _solve(kernels, imgs, lighting, cand, n_in, rho_in, use_in,
                      scale=scale, start=scale if scale is not None else initial_scale,
                      fit=fit, iterations=iterations, tol=tol)


def _nothing_valid(shape: tuple[int, int], scale: float | None) -> HKResult:
    h, w = shape
    return HKResult(
        normals=np.zeros((h, w, 3), np.float32), albedo=np.zeros((h, w), np.float32),
        scale=float("nan") if scale is None else float(scale),
        valid=np.zeros((h, w), bool), residual_rms=np.zeros((h, w), np.float32),
        iterations=0, cost_history=(0.0,),
    )


def _solve(
    kernels: _Kernels, imgs: np.ndarray, lighting: HKLighting, cand: np.ndarray,
    normals_in: np.ndarray, albedo_in: np.ndarray, usable: np.ndarray | None, *,
    scale: float | None, start: float | None, fit: bool, iterations: int, tol: float,
) -> HKResult:
    """The mask's pixels ``cand`` gathered into the passes' layout
    (:mod:`photometric.hk_model_kernel`), the passes, and the result images, each a compiled
    loop over the pixels."""
    k, h, w = imgs.shape
    hw = h * w
    f32 = np.float32
    # A camera's uint8 images are read as they are (the kernels convert each value; integers
    # are exact in float32); other integers become float32.
    if imgs.dtype not in (np.uint8, np.float32, np.float64):
        imgs = imgs.astype(f32)
    imgs = np.ascontiguousarray(imgs).reshape(k, hw)
    use_in = (imgs > 0 if usable is None else np.ascontiguousarray(usable).reshape(k, hw))
    n_in = _float_array(normals_in, (hw, 3))
    rho_in = _float_array(albedo_in, (hw,))
    if cand.size == 0:
        return _nothing_valid((h, w), scale)
    layout = kernels.model
    chunks = -(-cand.size // layout.CHUNK)
    if not fit:
        return _solve_held(kernels, imgs, lighting, cand, n_in, rho_in, use_in, chunks,
                           scale=float(scale), iterations=iterations, tol=tol)
    padded = chunks * layout.CHUNK
    meas = np.empty((chunks, k, layout.N_MEAS, layout.CHUNK), f32)
    v_dirs = np.empty((3, padded), f32)
    n0 = np.empty((3, padded), f32)
    rho0 = np.empty(padded, f32)
    solved = np.empty(cand.size, bool)
    counts = np.empty(cand.size, np.float64)
    flags = np.empty(chunks, np.uint8)
    kernels.gather.gather(cand, lighting.index, imgs, use_in, n_in, rho_in, lighting.terms,
                          lighting.views, lighting.bad, MIN_INIT_CR, meas, v_dirs, n0, rho0,
                          solved, counts, flags)
    if not solved.any():
        return _nothing_valid((h, w), scale)
    _check_flags(layout, flags)
    passes = JointPasses(kernels.passes, (meas, v_dirs), consts=kernel_consts(layout),
                         tau=float(lighting.params.optical_depth), n=n0, rho=rho0)
    a_scale, history, done = fit_jointly(passes, scale=start, iterations=iterations, tol=tol)
    normals = np.zeros((hw, 3), np.float32)
    albedo = np.zeros(hw, np.float32)
    rms = np.zeros(hw, np.float32)
    valid = np.zeros(hw, bool)
    kernels.passes.finish(cand, solved, passes.n, passes.rho, passes.sums, counts, normals,
                         albedo, rms, valid)
    return HKResult(
        normals=normals.reshape(h, w, 3), albedo=albedo.reshape(h, w), scale=float(a_scale),
        valid=valid.reshape(h, w), residual_rms=rms.reshape(h, w), iterations=done,
        cost_history=tuple(history), refit_scale=float(a_scale), mean_iterations=float(done),
    )


def _solve_held(
    kernels: _Kernels, imgs: np.ndarray, lighting: HKLighting, cand: np.ndarray,
    normals_in: np.ndarray, albedo_in: np.ndarray, usable: np.ndarray, chunks: int, *,
    scale: float, iterations: int, tol: float,
) -> HKResult:
    """:func:`_solve` with A held at ``scale``: the pixels are independent, so one compiled
    pass gathers, solves and writes out each chunk while it is in the core's cache
    (:func:`photometric.hk_passes_kernel.solve_held`), and A's linear fit at the solution is
    the ``refit_scale`` for the next burst."""
    hw = imgs.shape[1]
    h, w = lighting.shape
    solved = np.zeros(cand.size, bool)
    counts = np.zeros(cand.size, np.float64)
    normals = np.zeros((hw, 3), np.float32)
    albedo = np.zeros(hw, np.float32)
    rms = np.zeros(hw, np.float32)
    valid = np.zeros(hw, bool)
    flags = np.zeros(chunks, np.uint8)
    parts = np.zeros((chunks, 5), np.float64)
    tau = float(lighting.params.optical_depth)
    kernels.passes.solve_held(cand, lighting.index, imgs, usable, normals_in, albedo_in,
                            lighting.terms, lighting.views, lighting.bad, MIN_INIT_CR, scale,
                            np.float32(scale * tau), np.float32(-tau),
                            kernel_consts(kernels.model), np.float32(LAMBDA_START),
                            iterations, tol, solved, counts, normals, albedo, rms, valid,
                            flags, parts)
    _check_flags(kernels.model, flags)
    if not solved.any():
        return _nothing_valid((h, w), scale)
    initial, final, _, num, den = parts.sum(axis=0)
    return HKResult(
        normals=normals.reshape(h, w, 3), albedo=albedo.reshape(h, w), scale=scale,
        valid=valid.reshape(h, w), residual_rms=rms.reshape(h, w),
        iterations=int(parts[:, 2].max()), cost_history=(float(initial), float(final)),
        refit_scale=max(num / den, 0.0) if den > 0 else scale,
        mean_iterations=float(parts[:, 2].mean()),
    )


def _check_flags(kernel: ModuleType, flags: np.ndarray) -> None:
    """Raise if the ``bad`` bits of the solved pixels (per chunk) flag a direction (bits of
    ``kernel``, :mod:`photometric.hk_model_kernel`)."""
    bits = int(np.bitwise_or.reduce(flags))
    for name, non_finite, zero in (
        ("lights", kernel.BAD_LIGHT, kernel.ZERO_LIGHT),
        ("views", kernel.BAD_VIEW, kernel.ZERO_VIEW),
    ):
        if bits & non_finite:
            raise FingerpsReconError(
                f"{name} contain non-finite values inside the mask; check the calibration")
        if bits & zero:
            raise FingerpsReconError(f"{name} contain zero vectors inside the mask")


def _float_array(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``a`` reshaped, C-contiguous, float32 or float64 (other dtypes as float64): the
    dtypes the kernels are compiled for."""
    a = np.asarray(a)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    return np.ascontiguousarray(a).reshape(shape)


