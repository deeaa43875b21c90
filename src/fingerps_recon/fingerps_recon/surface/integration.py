"""Depth from normals: masked Poisson integration and back-projection to 3D points.

The paper shows 3D models but does not say how it integrates the normals (NOTES §5); this
module supplies the standard step, for an orthographic camera (:func:`integrate_normals`)
and for the pinhole camera of the rig (:func:`integrate_normals_perspective`).

Equations
---------
Orthographic camera. A unit normal n = (nx, ny, nz) in the PS frame (x right, y up, z towards
the camera) of a height field h(x, y) gives the gradients p = dh/dx = -nx/nz and
q = dh/dy = -ny/nz; nz is clamped from below (``min_nz``) so that grazing normals do not give
unbounded slopes. In image axes (column u to the right, row v *downwards*, y = -v) the
height changes by ``p * pixel_size_m`` per column and by ``-q * pixel_size_m`` per row.

Pinhole camera (the log-depth formulation of Durou et al. / Quéau et al.). The surface point
seen by pixel (u, v) is P = z r with r = (x_n, y_n, 1), y_n = (v - cy) / fy,
x_n = (u - cx - s y_n) / fx (optical frame, K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]), so
dP/du = z_u r + z (1/fx, 0, 0) and dP/dv = z_v r + z (-s/(fx fy), 1/fy, 0). Both are
orthogonal to the normal; with z~ = log z, the PS-frame normal n = (nx, ny, nz) and
D = nz - nx x_n + ny y_n = -(n_optical . r) > 0 for a surface facing the camera:

    dz~/du = nx / (fx D),        dz~/dv = -(ny + s nx / fx) / (fy D).

D / (|n| |r|) is the cosine between the normal and the direction towards the camera, clamped
from below by ``min_nz`` as nz is in the orthographic case. Near the optical axis
(x_n, y_n -> 0) this is the orthographic slope divided by the depth. Log-depth is fixed up to
one additive constant per connected component, i.e. depth up to a scale, which the working
distance fixes (the geometric mean of the depth over each component is the working distance).

Least squares
-------------
Both cases give per-pixel steps (du, dv) of the unknown (height in pixels, or log-depth) per
column and per row. Every pair of 4-neighbours that are both inside the mask is one equation
h_j - h_i = (g_i + g_j) / 2 (the mean of the two pixels' steps along the edge). The
least-squares solution of these equations is the masked Poisson equation with natural
(Neumann) boundary conditions on the mask's own outline: A h = D^T g, with A = D^T D the graph
Laplacian of the mask. Nothing outside the mask enters, so the background and the mask's
edge do not bend the surface, unlike a Frankot–Chellappa solve over the whole image.

Solvers (:class:`IntegrationMethod`)
------------------------------------
Both solve that same masked system by conjugate gradients preconditioned with the
pseudo-inverse of the Neumann Laplacian L of a bounding *rectangle* (the discrete
Frankot–Chellappa solver, diagonal in the DCT-II basis): the residual is extended by zero to
the rectangle, solved there and restricted back. This fictitious-domain preconditioner suits
a Neumann problem: for a compact, fingertip-like mask the iteration count hardly grows with
its size. Applied to b it gives the Frankot–Chellappa solution on the rectangle with the
steps outside the mask set to zero; the iterations correct it for the mask's shape, a
smooth (discrete harmonic) correction driven from the mask's outline.

``EXACT`` (the reference): steps in float64, each connected component solved separately to
a relative residual of ``tol`` (default 1e-6) in float64 with a sparse matrix and a 2-D DCT
preconditioner on the component's rectangle; a component that has not converged after
``max_iter`` iterations (comb-like masks, long one-pixel tendrils: nearly one-dimensional
graphs) is solved by a sparse direct factorisation instead, and components of fewer than
``_SMALL_COMPONENT`` pixels by one joint sparse direct solve.

``FAST`` (the default): float32, the whole mask at once on its bounding box, in compiled
loops (:mod:`surface.integration_kernel`):

- One pass over the box computes each pixel's steps from its normal, b, the moments of b and
  the mask's runs (maximal horizontal segments of mask pixels). From the runs alone come the
  4-connected components (union-find), the *outline* (the mask pixels with a 4-neighbour in
  the rectangle but outside the mask) and the Gram matrix V^T A V of the monomials s^a t^b,
  1 <= a + b <= 5, in the box's coordinates s, t scaled to [-1, 1] (sums over the mask's
  edges, from prefix sums along the runs).
- Start: the polynomial q0 = V c closest to the solution in the A-norm, V^T A V c = V^T b:
  the smooth bulk of the surface, exactly the solution when that is such a polynomial (a
  tilted plane costs no iteration). The rest, A y = b - A q0, by conjugate gradients whose
  first step is taken whole (step length 1): the Frankot–Chellappa solution of the rest on
  the rectangle. Where a pixel and its four neighbours are all in the mask, A equals L, so
  from then on the residual is zero but on the outline pixels: the scalar products, A d and
  the residual's update cost a few thousand pixels, and the next preconditioner input is
  sparse.
- The preconditioner L^+: a DCT-II along the rows (pocketfft), a tridiagonal solve down each
  column (Thomas' algorithm for T + mu_k I, the pivots kept per row length), the inverse
  DCT: half the transforms of a 2-D DCT pair. Only the rows are rounded up to an
  FFT-friendly length (the rectangle is otherwise the mask's bounding box: the less outside
  the mask, the better the preconditioner). A sparse residual's row transform is summed
  directly from the few outline pixels of each row.
- End: the polynomial correction closest to the remaining error, V^T A V c = V^T r (the same
  Gram matrix; r on the outline), which takes out most of the smooth error the iterations
  leave. Then each component's mean is taken out and, for a depth, the exponential taken (a
  float64 Taylor polynomial, the exponent halved and the result squared as often as
  needed), in the pass that writes the output: with one component its mean is known
  before (the sums of the directions, kept by the steps, and the mask's moments of the
  polynomial), with several a second pass follows.

Each iteration costs one preconditioner application and one pass over the box. The
residual ``tol`` (default ``FAST_TOL`` = 3e-3) is relative to |b|. On the simulated finger
(172 000 pixels, bounding box 432 x 459) that is 3 preconditioner applications, and FAST
differs from ``EXACT`` by ~0.07 um RMS (depths spanning 5 mm), far below the error against
the true surface (~1 um from the true normals with the perspective model, 100-200 um with
the orthographic one or from Lambertian normals); ``tol`` = 1e-4 takes 5 and differs by
~0.015 um. Speed and accuracy figures: ``bench/bench_recon_speed.py``. If it has not
converged after ``min(max_iter, FAST_MAX_ITER)`` preconditioner applications (the comb-like
masks ``EXACT`` solves directly) it falls back to ``EXACT``. The arrays of the box are kept
per thread for the next call (fresh memory would cost its page faults every burst).

Each component is given zero mean height (its offset is not observable), so the whole result
has zero mean inside the mask.

Metric scale of points comes from the camera intrinsics and the working distance:
:func:`height_to_distance` turns heights into distances along the optical axis and
:func:`depth_to_points` back-projects them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from enum import Enum
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.mask_box import mask_bounding_box
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface import integration_kernel as kernels
from fingerps_recon.surface.back_projection_kernel import back_project

_SMALL_COMPONENT = 2048

#: Default relative residual of the FAST solver.
FAST_TOL = 3e-3
#: Iteration (preconditioner application) limit of the FAST solver before it falls back to
#: the EXACT one.
FAST_MAX_ITER = 30
#: Default relative residual of the EXACT solver.
EXACT_TOL = 1e-6

# Threads for the DCTs of the FAST solver. Two (the machine's cores) gained nothing inside the
# solver: between DCTs pocketfft's second thread sleeps, and waking it cost about what it
# saved (more on a loaded machine); one thread leaves the other core to the rest of the node.
_FFT_WORKERS = 1


class IntegrationMethod(Enum):
    """Solver of the masked Poisson equation (see the module docstring)."""

    FAST = "fast"
    """Bounding-box PCG in float32 from a polynomial start, to ``FAST_TOL``; the default."""
    EXACT = "exact"
    """Per-component PCG in float64 with a sparse matrix to ``EXACT_TOL``, direct fallback."""


def integrate_normals(
    normals: np.ndarray,
    *,
    mask: np.ndarray,
    pixel_size_m: float,
    min_nz: float = 0.1,
    tol: float | None = None,
    max_iter: int = 100,
    method: IntegrationMethod = IntegrationMethod.FAST,
) -> np.ndarray:
    """Integrate a normal map into a height map by a masked Poisson solve (orthographic).

    Parameters
    ----------
    normals : (H, W, 3) float
        Normals in the PS frame (x right, y up, z towards the camera). They need not be unit
        length; pixels whose normal is zero or not finite contribute a zero slope.
    mask : (H, W) bool
        Pixels to integrate over. Pass ``mask & valid`` to leave out pixels without a normal.
    pixel_size_m : float
        Size of one pixel on the object in metres (orthographic scale), > 0.
    min_nz : float
        Lower clamp of the unit normal's z component, in (0, 1]; limits slopes to
        sqrt(1 - min_nz**2) / min_nz (0.1 -> about 84 degrees).
    tol : float, optional
        Relative residual at which the conjugate-gradient iterations stop; default
        ``FAST_TOL`` (3e-3) or ``EXACT_TOL`` (1e-6) by ``method``.
    max_iter : int
        Conjugate-gradient iteration limit (per connected component for ``EXACT``); a
        problem that has not converged by then is solved by a sparse direct factorisation
        instead. ``FAST`` stops at ``min(max_iter, FAST_MAX_ITER)`` and then hands over to
        ``EXACT``.
    method : IntegrationMethod
        ``FAST`` (default) or ``EXACT``; both solve the same equations.

    Returns
    -------
    height : (H, W) float32
        Height in metres along the PS z axis (towards the camera: a bump is positive), with
        zero mean inside each connected component of the mask, NaN outside the mask.

    Raises
    ------
    FingerpsReconError
        On bad shapes or options, or if the heights come out non-finite.
    """
    n, m = _checked(normals, mask, min_nz=min_nz, tol=tol, max_iter=max_iter, method=method)
    if not (np.isfinite(pixel_size_m) and pixel_size_m > 0):
        raise FingerpsReconError(f"pixel_size_m must be a positive number, got {pixel_size_m}")
    box = mask_bounding_box(m)
    if box is None:
        return np.full(m.shape, np.nan, dtype=np.float32)
    height = _output(m.shape, box)
    _solve(_orthographic_steps(n, box, min_nz=float(min_nz)), m, box, method=method, tol=tol,
           max_iter=max_iter, out=height, scale=pixel_size_m, offset=0.0, exponential=False,
           exact_steps=lambda: _slopes(n[box], m[box], min_nz=float(min_nz)))
    return height


def integrate_normals_perspective(
    normals: np.ndarray,
    *,
    mask: np.ndarray,
    camera_matrix: np.ndarray,
    working_distance_m: float,
    min_nz: float = 0.1,
    tol: float | None = None,
    max_iter: int = 100,
    method: IntegrationMethod = IntegrationMethod.FAST,
) -> np.ndarray:
    """Integrate a normal map into a depth map for a pinhole camera (log-depth Poisson).

    The log-depth formulation in the module docstring: the normals give the gradient of
    log z per pixel, a masked Poisson solve integrates it, and the depth follows up to a
    scale per connected component, fixed by ``working_distance_m``.

    Parameters
    ----------
    normals : (H, W, 3) float
        Normals in the PS frame (x right, y up, z towards the camera); need not be unit
        length; zero or non-finite normals contribute a zero gradient.
    mask : (H, W) bool
        Pixels to integrate over.
    camera_matrix : (3, 3) float
        Intrinsics K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels.
    working_distance_m : float
        Geometric mean of the depth over each connected component of the mask (its mean
        log-depth is log(working_distance_m)), metres, > 0.
    min_nz : float
        Lower clamp of the cosine between the unit normal and the direction from the
        surface point towards the camera (the perspective counterpart of n_z), in (0, 1].
    tol, max_iter, method
        As for :func:`integrate_normals`.

    Returns
    -------
    depth : (H, W) float32
        Distance along the optical axis (optical z, metres) of each pixel's surface point,
        NaN outside the mask; ready for :func:`depth_to_points`.

    Raises
    ------
    FingerpsReconError
        On bad shapes or options, or if the depths come out non-finite.
    """
    n, m = _checked(normals, mask, min_nz=min_nz, tol=tol, max_iter=max_iter, method=method)
    k = checked_camera_matrix(camera_matrix)
    if not (np.isfinite(working_distance_m) and working_distance_m > 0):
        raise FingerpsReconError(
            f"working_distance_m must be a positive number, got {working_distance_m}"
        )
    box = mask_bounding_box(m)
    if box is None:
        return np.full(m.shape, np.nan, dtype=np.float32)
    steps = _perspective_steps(n, k, box, min_nz=float(min_nz))
    depth = _output(m.shape, box)
    _solve(steps, m, box, method=method, tol=tol, max_iter=max_iter, out=depth, scale=1.0,
           offset=float(np.log(working_distance_m)), exponential=True,
           exact_steps=lambda: _log_depth_slopes(n, m, k, box, min_nz=float(min_nz)))
    return depth


def _output(shape: tuple[int, int], box: tuple[slice, slice]) -> np.ndarray:
    """(H, W) float32, NaN outside ``box``; the box is left for the solver to write."""
    out = np.empty(shape, dtype=np.float32)
    rows, cols = box
    out[: rows.start] = np.nan
    out[rows.stop :] = np.nan
    out[rows, : cols.start] = np.nan
    out[rows, cols.stop :] = np.nan
    return out


# ----------------------------------------------------------------------------- checks


def _checked(
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    min_nz: float,
    tol: float | None,
    max_iter: int,
    method: IntegrationMethod,
) -> tuple[np.ndarray, np.ndarray]:
    n = np.asarray(normals)
    m = np.ascontiguousarray(mask)
    if n.ndim != 3 or n.shape[2] != 3:
        raise FingerpsReconError(f"normals must have shape (H, W, 3), got {n.shape}")
    if m.shape != n.shape[:2]:
        raise FingerpsReconError(
            f"mask shape {m.shape} does not match normals shape {n.shape}; pass an (H, W) mask"
        )
    if m.dtype != bool:
        raise FingerpsReconError(f"mask must be a bool array, got dtype {m.dtype}")
    if not 0 < min_nz <= 1:
        raise FingerpsReconError(f"min_nz must be in (0, 1], got {min_nz}")
    if (tol is not None and not tol > 0) or max_iter < 1:
        raise FingerpsReconError(f"need tol > 0 and max_iter >= 1, got {tol}, {max_iter}")
    if not isinstance(method, IntegrationMethod):
        raise FingerpsReconError(
            f"method must be an IntegrationMethod (FAST or EXACT), got {method!r}"
        )
    return n, m


# ----------------------------------------------------------------------------- steps


def _slopes(
    normals: np.ndarray, mask: np.ndarray, *, min_nz: float
) -> tuple[np.ndarray, np.ndarray]:
    """Height steps per column (du) and per row (dv), in pixels, from PS-frame normals."""
    n = normals.astype(np.float64)
    norm = np.linalg.norm(n, axis=2)
    usable = mask & np.isfinite(norm) & (norm > 0)
    safe_norm = np.where(usable, norm, 1.0)
    nx = np.where(usable, n[..., 0] / safe_norm, 0.0)
    ny = np.where(usable, n[..., 1] / safe_norm, 0.0)
    nz = np.where(usable, n[..., 2] / safe_norm, 1.0)
    nz = np.maximum(nz, min_nz)
    p = -nx / nz  # dh/dx, x to the right = +column
    q = -ny / nz  # dh/dy, y up = -row
    return p, -q


class _Steps(NamedTuple):
    """The arguments from which the FAST kernel computes each pixel's steps (du, dv): D =
    max(nz - nx x_n + ny y_n, min_nz |n| |r|), du = nx / (fx D),
    dv = -(ny + skew nx) / (fy D) (:func:`surface.integration_kernel.assemble_rhs`)."""

    normals: np.ndarray  # (H, W, 3) float32, C-contiguous
    x_n: np.ndarray      # (1, w) or (h, w) float32
    y_n: np.ndarray      # (h,) float32
    skew: np.float32
    min_nz: np.float32
    fx: np.float32
    fy: np.float32


def _perspective_steps(
    normals: np.ndarray, camera_matrix: np.ndarray, box: tuple[slice, slice], *, min_nz: float
) -> _Steps:
    """Steps of log depth per column and per row (module docstring) on ``box``."""
    fx, s, cx = (float(c) for c in camera_matrix[0])
    fy, cy = float(camera_matrix[1, 1]), float(camera_matrix[1, 2])
    rows, cols = box
    y_n = (np.arange(rows.start, rows.stop) - cy) / fy  # (h,)
    x_n = ((np.arange(cols.start, cols.stop) - cx) / fx)[None, :]  # (1, w), (h, w) with skew
    if s != 0.0:
        x_n = x_n - (s / fx) * y_n[:, None]
    f32 = np.float32
    return _Steps(np.ascontiguousarray(normals, dtype=f32), x_n.astype(f32), y_n.astype(f32),
                  f32(s / fx), f32(min_nz), f32(fx), f32(fy))


def _orthographic_steps(normals: np.ndarray, box: tuple[slice, slice], *,
                        min_nz: float) -> _Steps:
    """Height steps in pixels per column and per row (module docstring) on ``box``: the
    perspective formula with x_n = y_n = 0 and fx = fy = -1, du = -nx / max(nz, min_nz |n|),
    dv = ny / max(nz, min_nz |n|)."""
    rows, cols = box
    f32 = np.float32
    return _Steps(np.ascontiguousarray(normals, dtype=f32),
                  np.zeros((1, cols.stop - cols.start), dtype=f32),
                  np.zeros(rows.stop - rows.start, dtype=f32), f32(0.0), f32(min_nz),
                  f32(-1.0), f32(-1.0))


def _log_depth_slopes(
    normals: np.ndarray,
    mask: np.ndarray,
    camera_matrix: np.ndarray,
    box: tuple[slice, slice],
    *,
    min_nz: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Steps of log depth per column and per row (module docstring), float64, on ``box`` of
    the (H, W, 3) ``normals`` and (H, W) ``mask``: the EXACT solver's (the FAST one computes
    them in float32 in its kernel); 0 where a normal is zero or not finite."""
    fx, s, cx = (float(c) for c in camera_matrix[0])
    fy, cy = float(camera_matrix[1, 1]), float(camera_matrix[1, 2])
    rows, cols = box
    n = normals[box].astype(np.float64)
    y_n = ((np.arange(rows.start, rows.stop) - cy) / fy)[:, None]
    x_n = (np.arange(cols.start, cols.stop) - cx) / fx - (s / fx) * y_n
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        norm = np.linalg.norm(n, axis=2)
        usable = mask[box] & np.isfinite(norm) & (norm > 0)
        nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
        ray = np.sqrt(x_n * x_n + y_n * y_n + 1.0)
        den = np.maximum(nz - nx * x_n + ny * y_n, min_nz * ray * norm)
        du = np.where(usable, nx / (fx * den), 0.0)
        dv = np.where(usable, -(ny + (s / fx) * nx) / (fy * den), 0.0)
    return du, dv


# ----------------------------------------------------------------------------- solvers


def _solve(
    steps: _Steps,
    mask: np.ndarray,
    box: tuple[slice, slice],
    *,
    method: IntegrationMethod,
    tol: float | None,
    max_iter: int,
    out: np.ndarray,
    scale: float,
    offset: float,
    exponential: bool,
    exact_steps: Callable[[], tuple[np.ndarray, np.ndarray]],
) -> None:
    """Least-squares integration of the steps over the mask; writes ``out[box]``.

    ``steps``: how the FAST solver computes the steps of the box ``box`` of ``mask``
    (H, W) bool, C-contiguous; ``exact_steps()``: the same steps as two (h, w) float64
    arrays for ``EXACT`` (to which ``FAST`` hands over if it does not converge). ``out``
    (H, W) float32: on the box, ``scale * solution + offset`` on the mask (the solution with
    zero mean per 4-connected component) and NaN elsewhere, or with ``exponential``
    exp(scale * solution + offset); outside the box left as it is.
    """
    if method is IntegrationMethod.FAST and _solve_fast(
        steps, mask, box, tol=FAST_TOL if tol is None else tol,
        max_iter=min(max_iter, FAST_MAX_ITER), out=out, scale=scale, offset=offset,
        exponential=exponential,
    ):
        return
    inside = mask[box]
    du, dv = exact_steps()
    values = _solve_exact(du, dv, inside, tol=EXACT_TOL if tol is None else tol,
                          max_iter=max_iter)
    if not np.all(np.isfinite(values)):
        raise FingerpsReconError(_NON_FINITE)
    view = out[box]
    view[...] = np.nan
    view[inside] = scale * values + offset
    if exponential:
        np.exp(view, out=view)


_NON_FINITE = ("normal integration produced non-finite values; check that the normals "
               "inside the mask are finite")


def _solve_fast(
    steps: _Steps,
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
    """The ``FAST`` solver (module docstring): writes ``out[box]`` as :func:`_solve` does and
    returns True, or returns False (``out`` untouched) if the relative residual is still
    above ``tol`` after ``max_iter`` preconditioner applications."""
    rows, cols = box
    r0, c0 = rows.start, cols.start
    h, w = rows.stop - r0, cols.stop - c0
    shape = (h, scipy.fft.next_fast_len(w, real=True))  # DCT along rows only
    inside = mask.view(np.uint8)
    poly = _poly_tables(h, w)
    ws = _workspace(h, w, shape)
    buf = ws.buf  # b, then each preconditioner application's input and output
    n_runs, b_norm2 = kernels.assemble_rhs(
        steps.normals, inside, r0, c0, h, w, steps.x_n, steps.y_n, steps.skew, steps.min_nz,
        steps.fx, steps.fy, poly.row_powers, buf, ws.col_moments, ws.run_start, ws.run_stop,
        ws.row_first)
    run_start, run_stop = ws.run_start[:n_runs], ws.run_stop[:n_runs]
    labels = np.empty(n_runs, dtype=np.int32)
    gram = np.empty((_A.size, _A.size))
    mask_moments = np.empty((_POLY_DEGREE + 1, _POLY_DEGREE + 1))
    n_comp, n_out = kernels.run_topology(
        run_start, run_stop, ws.row_first, shape[1], poly.pair_prefix, poly.power_prefix,
        poly.row_powers, poly.row_steps, _A, _B, labels, ws.outline_rows, ws.outline_cols,
        gram, mask_moments, ws.segments[0], ws.segments[1])
    outline_rows, outline_cols = ws.outline_rows[:n_out], ws.outline_cols[:n_out]

    # The start: the best polynomial of degree <= _POLY_DEGREE in the A-norm, q0 = V c,
    # from V^T A V c = V^T b (V^T b: the moments of b).
    gram_inverse = _inverse(gram)
    moments = np.empty(_A.size)
    kernels.column_moments(ws.col_moments, poly.col_powers, _A, _B, moments)
    coef = gram_inverse @ moments
    r_norm2 = kernels.subtract_poly_laplacian(buf, inside, r0, c0, h, w, _coef_table(coef),
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
    cosines = _cosines(shape[1])
    pivots = _column_pivots(shape)
    while not converged and applied < max_iter:
        _precondition(buf, pivots, transformed=applied > 0)
        if applied > 0:
            rz = kernels.outline_dot(buf, outline_rows, outline_cols, n_out, residual)
        # the second step restarts (beta = 0): the first one's length was not rz / d_ad
        beta = np.float32(rz / rz_old if applied > 1 and rz_old > 0.0 else 0.0)
        d_sum = kernels.take_direction(buf, inside, r0, c0, x, d, alpha, beta, applied)
        d_ad = kernels.outline_laplacian(d, inside, r0, c0, outline_rows, outline_cols,
                                         n_out, product)
        if applied > 0 and not d_ad > 0.0:  # no descent left: cannot reach tol
            break
        alpha = np.float32(rz / d_ad if applied > 0 else 1.0)
        x_sum += float(alpha) * d_sum
        r_norm2 = kernels.outline_update(residual, product, alpha, n_out)
        rz_old = rz
        applied += 1
        converged = r_norm2 <= limit
        if not converged and applied < max_iter:  # the next step's input, transformed
            kernels.outline_spectrum(residual, buf, outline_rows, outline_cols, n_out,
                                     cosines)
    if not converged:
        return False
    if applied:  # the best polynomial correction of the remaining error: V^T A V c = V^T r
        kernels.outline_moments(residual, outline_rows, outline_cols, n_out, poly.row_powers,
                                poly.col_powers, _A, _B, moments)
        coef += gram_inverse @ moments
    table = _coef_table(coef)
    counts = np.bincount(labels, weights=run_stop - run_start, minlength=n_comp)
    final = n_comp == 1  # the mean is known: x's sum and q's from the mask's moments
    center = np.array([(x_sum + float(np.sum(table * mask_moments))) / counts[0]])
    sums = np.zeros(n_comp)
    kernels.write_solution(x, d, alpha, applied, run_start, run_stop, ws.row_first, labels,
                           table, poly.row_powers, poly.col_powers[1], out, r0, c0, sums,
                           center, float(scale), float(offset), exponential, final)
    if not final:
        center = sums / counts
        kernels.finish_runs(out, r0, c0, h, w, run_start, run_stop, ws.row_first, labels,
                            center, float(scale), float(offset), exponential)
    if not np.all(np.isfinite(center)):
        raise FingerpsReconError(_NON_FINITE)
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
        deg = _POLY_DEGREE
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


def _inverse(gram: np.ndarray) -> np.ndarray:
    """Inverse of the symmetric positive semi-definite ``gram``, or its pseudo-inverse
    (eigenvalues below 1e-12 of the largest count as zero) when it is singular: a mask too
    small or thin for some monomials."""
    inverse = np.empty_like(gram)
    if kernels.spd_inverse(gram, inverse):
        return inverse
    values, vectors = np.linalg.eigh(gram)
    keep = values > 1e-12 * max(values[-1], 0.0)
    return (vectors[:, keep] / values[keep]) @ vectors[:, keep].T


def _precondition(buf: np.ndarray, pivots: tuple[np.ndarray, np.ndarray], *,
                 transformed: bool = False) -> None:
    """buf = L^+ buf in place, L the Neumann Laplacian of the box (buf's shape): a DCT-II
    along the rows (unless ``transformed``: buf holds it already), a tridiagonal solve down
    each column (``pivots``: :func:`_column_pivots` of the shape), the inverse DCT."""
    if not transformed:
        spec = scipy.fft.dct(buf, type=2, axis=1, norm="ortho", workers=_FFT_WORKERS,
                             overwrite_x=True)
        if spec.ctypes.data != buf.ctypes.data:  # pocketfft works in place; if it ever
            buf[...] = spec                      # does not
    kernels.neumann_columns(buf, *pivots)
    z = scipy.fft.idct(buf, type=2, axis=1, norm="ortho", workers=_FFT_WORKERS,
                       overwrite_x=True)
    if z.ctypes.data != buf.ctypes.data:
        buf[...] = z


@lru_cache(maxsize=4)
def _cosines(w2: int) -> np.ndarray:
    """(w2, w2) float32 [c, j]: the orthonormal DCT-II of a row of w2 pixels is
    sum over c of row[c] cosines[c, j] (scipy.fft.dct(norm="ortho")); read-only."""
    c = np.arange(w2)[:, None]
    j = np.arange(w2)[None, :]
    table = np.cos(np.pi * j * (2 * c + 1) / (2 * w2)) * np.sqrt(2.0 / w2)
    table[:, 0] = np.sqrt(1.0 / w2)
    table = table.astype(np.float32)
    table.setflags(write=False)
    return table


def _column_shifts(w2: int) -> np.ndarray:
    """mu_k = 2 - 2 cos(pi k / w2): the eigenvalues of the Neumann second difference along
    a row of w2 pixels in the DCT-II basis."""
    return 2.0 - 2.0 * np.cos(np.pi * np.arange(w2) / w2)


_PIVOTS: dict[int, tuple[np.ndarray, np.ndarray]] = {}
_PIVOTS_LOCK = threading.Lock()


def _pivots(w2: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Pivots p_i (float64) and 1 / p_i (float32, column 0 zero) of Thomas' algorithm for
    T + mu_k I, rows 0..rows - 1 of a T taller than the box (row 0's diagonal 1 + mu, the
    next ones' 2 + mu: the last row of a box differs, :func:`_last_pivots`). Kept per w2 and
    grown when a taller box comes (the recurrence runs down the rows)."""
    with _PIVOTS_LOCK:
        pivots, inverse = _PIVOTS.get(w2, (np.empty((0, w2)), np.empty((0, w2), np.float32)))
        if pivots.shape[0] < rows:
            mu = _column_shifts(w2)
            grown = np.empty((rows + 64, w2))  # room for a few more rows
            grown[: pivots.shape[0]] = pivots
            start = pivots.shape[0]
            if start == 0:
                grown[0] = 1.0 + mu
                start = 1
            for i in range(start, grown.shape[0]):
                grown[i] = 2.0 + mu - 1.0 / grown[i - 1]
            inverse = (1.0 / grown).astype(np.float32)
            inverse[:, 0] = 0.0
            pivots = grown
            for table in (pivots, inverse):
                table.setflags(write=False)
            _PIVOTS[w2] = (pivots, inverse)
        return pivots, inverse


@lru_cache(maxsize=8)
def _column_pivots(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """For a box of ``shape`` (h, w2): (>= h - 1, w2) float32 1 / p_i of rows 0..h - 2
    (:func:`_pivots`) and (w2,) float32 1 / p of the last row (its diagonal 1 + mu, or mu
    alone for one row); column 0 zero (solved apart). Read-only, kept for the next bursts
    of the same box size."""
    h, w2 = shape
    inverse = _pivots(w2, max(h - 1, 1))[1]
    mu = _column_shifts(w2)
    mu[0] = 1.0  # column 0 is solved apart; keep its division finite
    if h == 1:
        last = mu
    else:
        last = 1.0 + mu - 1.0 / _pivots(w2, h - 1)[0][h - 2]
    last_inverse = (1.0 / last).astype(np.float32)
    last_inverse[0] = 0.0
    last_inverse.setflags(write=False)
    return inverse, last_inverse


# ----------------------------------------------------------------------------- polynomials

#: Degree of the polynomial space of the FAST solver's start and last correction.
_POLY_DEGREE = kernels.POLY_DEGREE
# Its basis: monomials s^a t^b, 1 <= a + b <= _POLY_DEGREE (the constant is free), as the
# pairs (_A[i], _B[i]).
_BASIS = [(a, t - a) for t in range(1, _POLY_DEGREE + 1) for a in range(t + 1)]
_A = np.array([a for a, _ in _BASIS])
_B = np.array([b for _, b in _BASIS])


class _PolyTables(NamedTuple):
    """Tables of the polynomial space on an h x w box (:func:`_poly_tables`)."""

    col_powers: np.ndarray    # (D + 1, w) s(c)^a
    row_powers: np.ndarray    # (h, 2 D + 1) t(r)^k
    pair_prefix: np.ndarray   # (w, D * D) prefix sums over c of Dh_a(c) Dh_a'(c)
    power_prefix: np.ndarray  # (w + 1, 2 D + 1) prefix sums over c of s(c)^k
    row_steps: np.ndarray     # (h - 1, D * D) Dv_b(r) Dv_b'(r)


@lru_cache(maxsize=8)
def _poly_tables(h: int, w: int) -> _PolyTables:
    """Coordinates s = (c - (w - 1) / 2) / ((w - 1) / 2), t likewise for rows (in [-1, 1]),
    their powers, and the steps of the monomials along an edge: Dh_a(c) = s(c + 1)^a -
    s(c)^a (a = 1..D) between columns c and c + 1, Dv_b(r) likewise between rows
    (:func:`surface.integration_kernel.poly_tables`); read-only, kept for the next bursts
    of the same box size."""
    deg = _POLY_DEGREE
    tables = _PolyTables(np.empty((deg + 1, w)), np.empty((h, 2 * deg + 1)),
                         np.empty((w, deg * deg)), np.empty((w + 1, 2 * deg + 1)),
                         np.empty((max(h - 1, 0), deg * deg)))
    kernels.poly_tables(*tables)
    for table in tables:
        table.setflags(write=False)
    return tables


def _coef_table(coef: np.ndarray) -> np.ndarray:
    """(D + 1, D + 1) float64 table[a, b] of the polynomial sum_i coef[i] s^_A[i] t^_B[i]."""
    table = np.zeros((_POLY_DEGREE + 1, _POLY_DEGREE + 1))
    table[_A, _B] = coef
    return table


def _solve_exact(
    du: np.ndarray, dv: np.ndarray, m: np.ndarray, *, tol: float, max_iter: int
) -> np.ndarray:
    """The reference solver (module docstring, ``EXACT``): values of the mask pixels.

    Returns the (N,) float64 solution over the mask pixels in raster order, zero mean per
    4-connected component.
    """
    n_pix = int(np.count_nonzero(m))
    # Number the mask pixels 0..N-1 in raster order.
    ids = np.full(m.shape, -1, dtype=np.int64)
    ids[m] = np.arange(n_pix)

    # Edges (i, j) between 4-neighbours inside the mask; equation h_j - h_i = g.
    hor = m[:, :-1] & m[:, 1:]
    ver = m[:-1, :] & m[1:, :]
    src = np.concatenate([ids[:, :-1][hor], ids[:-1, :][ver]])
    dst = np.concatenate([ids[:, 1:][hor], ids[1:, :][ver]])
    g = np.concatenate(
        [
            0.5 * (du[:, :-1][hor] + du[:, 1:][hor]),
            0.5 * (dv[:-1, :][ver] + dv[1:, :][ver]),
        ]
    )
    # A = D^T D (graph Laplacian), b = D^T g.
    deg = np.bincount(src, minlength=n_pix) + np.bincount(dst, minlength=n_pix)
    rows = np.concatenate([src, dst, np.arange(n_pix)])
    cols = np.concatenate([dst, src, np.arange(n_pix)])
    vals = np.concatenate([-np.ones(2 * src.size), deg.astype(np.float64)])
    lap = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(n_pix, n_pix))
    rhs = np.bincount(dst, weights=g, minlength=n_pix) - np.bincount(
        src, weights=g, minlength=n_pix
    )

    labels, n_comp = scipy.ndimage.label(m)  # 4-connectivity, as the edges above
    comp_of_pixel = labels[m] - 1
    sizes = np.bincount(comp_of_pixel, minlength=n_comp)
    solution = np.zeros(n_pix)

    vv, uu = np.nonzero(m)
    order = np.argsort(comp_of_pixel, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    small = []
    for c in range(n_comp):
        if sizes[c] < 2:
            continue
        idx = order[starts[c] : starts[c + 1]]
        if sizes[c] < _SMALL_COMPONENT:
            small.append(idx)
            continue
        sub = lap if sizes[c] == n_pix else lap[idx][:, idx]
        solution[idx] = _solve_component(
            sub, rhs[idx], vv[idx], uu[idx], tol=tol, max_iter=max_iter
        )
    if small:
        solution_small = _solve_small(lap, rhs, small)
        for idx, values in solution_small:
            solution[idx] = values

    # Zero mean per component (the offset of each is not observable).
    means = np.bincount(comp_of_pixel, weights=solution, minlength=n_comp) / np.maximum(sizes, 1)
    solution -= means[comp_of_pixel]
    return solution


def _solve_component(
    lap: scipy.sparse.csr_matrix,
    rhs: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    *,
    tol: float,
    max_iter: int,
) -> np.ndarray:
    """Solve one connected component: DCT-preconditioned CG, sparse direct if that stalls."""
    b = rhs - rhs.mean()  # exactly zero-sum in exact arithmetic; remove round-off
    b_norm = np.linalg.norm(b)
    if b_norm == 0:
        return np.zeros_like(b)
    x = _pcg_dct(lap, b, rows, cols, tol=tol * b_norm, max_iter=max_iter)
    if x is None:
        # Masks with long one-pixel tendrils or comb-like shapes defeat the rectangle
        # preconditioner; such graphs are nearly one-dimensional and factorise cheaply.
        x = np.zeros_like(b)
        sub = lap[1:, 1:].tocsc()  # pin the first pixel
        x[1:] = scipy.sparse.linalg.splu(sub, permc_spec="MMD_AT_PLUS_A").solve(b[1:])
    if not np.all(np.isfinite(x)):
        raise FingerpsReconError(
            "normal integration produced non-finite heights; check that the normals inside "
            "the mask are finite"
        )
    return x


def _pcg_dct(
    lap: scipy.sparse.csr_matrix,
    b: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    *,
    tol: float,
    max_iter: int,
) -> np.ndarray | None:
    """Conjugate gradients with the bounding rectangle's Neumann Laplacian as preconditioner.

    Returns None if the residual norm is still above ``tol`` after ``max_iter`` iterations.
    """
    r0, c0 = rows.min(), cols.min()
    # Any rectangle holding the component will do: take FFT-friendly (5-smooth) sides.
    box_shape = (
        scipy.fft.next_fast_len(int(rows.max() - r0 + 1), real=True),
        scipy.fft.next_fast_len(int(cols.max() - c0 + 1), real=True),
    )
    rr, cc = rows - r0, cols - c0
    # Eigenvalues of the 4-neighbour Neumann Laplacian of the rectangle in the DCT-II basis.
    ev = (2.0 - 2.0 * np.cos(np.pi * np.arange(box_shape[0]) / box_shape[0]))[:, None] + (
        2.0 - 2.0 * np.cos(np.pi * np.arange(box_shape[1]) / box_shape[1])
    )[None, :]
    ev[0, 0] = 1.0
    inv_ev = (1.0 / ev).astype(np.float32)
    inv_ev[0, 0] = 0.0  # the constant mode is free
    box = np.zeros(box_shape, dtype=np.float32)

    def precondition(res: np.ndarray) -> np.ndarray:
        box[rr, cc] = res
        spec = scipy.fft.dctn(box, type=2, norm="ortho")
        spec *= inv_ev
        z = scipy.fft.idctn(spec, type=2, norm="ortho")[rr, cc].astype(np.float64)
        return z - z.mean()  # stay in the range of the (singular) Laplacian

    x = np.zeros_like(b)
    r = b.copy()
    z = precondition(r)
    d = z.copy()
    rz = r @ z
    for _ in range(max_iter):
        ad = lap @ d
        alpha = rz / (d @ ad)
        x += alpha * d
        r -= alpha * ad
        if np.linalg.norm(r) <= tol:
            return x
        z = precondition(r)
        rz_new = r @ z
        d = z + (rz_new / rz) * d
        rz = rz_new
    return None


def _solve_small(
    lap: scipy.sparse.csr_matrix, rhs: np.ndarray, components: list[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Solve the small components jointly by one sparse direct solve, first pixel pinned."""
    free = np.concatenate([idx[1:] for idx in components])
    sub = lap[free][:, free].tocsc()
    values = np.zeros(lap.shape[0])
    values[free] = scipy.sparse.linalg.spsolve(sub, rhs[free])
    return [(idx, values[idx]) for idx in components]


def warm_up() -> None:
    """Compile (or load) every kernel of the ``FAST`` solver (:mod:`surface.integration_kernel`):
    a small mask of two components (only then does :func:`finish_runs` run) integrated to a
    tight tolerance (several steps), with the dtypes a reconstruction gives."""
    v, u = np.mgrid[0:24, 0:30]
    mask = (np.hypot(u - 8, v - 12) < 6) | (np.hypot(u - 22, v - 12) < 5)
    normals = np.zeros((24, 30, 3), dtype=np.float32)
    normals[..., 0] = np.where(mask, (u - 15) / 40.0, 0.0)
    normals[..., 1] = np.where(mask, (v - 12) / 50.0, 0.0)
    normals[..., 2] = 1.0
    k = np.array([[3000.0, 0.0, 15.0], [0.0, 3000.0, 12.0], [0.0, 0.0, 1.0]])
    integrate_normals_perspective(normals, mask=mask, camera_matrix=k, working_distance_m=0.09,
                                  tol=1e-6)


def height_to_distance(height_m: np.ndarray, *, working_distance_m: float) -> np.ndarray:
    """Distance along the optical axis from a height map (PS z towards the camera).

    Parameters
    ----------
    height_m : (H, W) float
        Heights from :func:`integrate_normals` (metres, positive towards the camera).
    working_distance_m : float
        Distance along the optical axis of the height map's zero level, metres, > 0.

    Returns
    -------
    distance : (H, W) float32
        ``working_distance_m - height_m``; NaN stays NaN.
    """
    if not (np.isfinite(working_distance_m) and working_distance_m > 0):
        raise FingerpsReconError(
            f"working_distance_m must be a positive number, got {working_distance_m}"
        )
    return (working_distance_m - np.asarray(height_m, dtype=np.float64)).astype(np.float32)


def depth_to_points(
    depth_m: np.ndarray, mask: np.ndarray, *, camera_matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth map into 3D points in the camera optical frame (pinhole model).

    Parameters
    ----------
    depth_m : (H, W) float
        Distance along the optical axis (optical z, metres) of each pixel, see
        :func:`height_to_distance` and :func:`integrate_normals_perspective`.
    mask : (H, W) bool
        Pixels to back-project; pixels whose depth is not finite or not > 0 are left out.
    camera_matrix : (3, 3) float
        Intrinsics K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels.

    Returns
    -------
    points : (N, 3) float32
        x = (u - cx - s*y_n) z / fx, y = (v - cy) z / fy, z = depth (optical frame, metres),
        with y_n = (v - cy) / fy, for the selected pixels in raster order.
    index : (N,) int64
        Flat index (v * W + u) of each point's pixel, e.g. ``image.ravel()[index]`` gives the
        matching intensities.
    """
    depth = np.asarray(depth_m)
    m = np.asarray(mask)
    if depth.ndim != 2:
        raise FingerpsReconError(f"depth_m must have shape (H, W), got {depth.shape}")
    if m.shape != depth.shape or m.dtype != bool:
        raise FingerpsReconError(
            f"mask must be a bool array of the depth's shape {depth.shape}, got {m.shape} {m.dtype}"
        )
    k = checked_camera_matrix(camera_matrix)
    fx, s, cx = k[0]
    fy, cy = k[1, 1], k[1, 2]
    box = mask_bounding_box(m)
    if box is None:
        return np.empty((0, 3), dtype=np.float32), np.empty(0, dtype=np.int64)
    rows, cols = box
    y_row = ((np.arange(rows.start, rows.stop) - cy) / fy).astype(np.float32)  # y_n
    x_col = ((np.arange(cols.start, cols.stop) - cx) / fx).astype(np.float32)  # x_n, no skew
    most = int(np.count_nonzero(m[box]))
    points = np.empty((most, 3), dtype=np.float32)
    index = np.empty(most, dtype=np.int64)
    count = back_project(np.ascontiguousarray(depth, dtype=np.float32), np.ascontiguousarray(m),
                         rows.start, cols.start, y_row, x_col, np.float32(s / fx), points, index)
    return points[:count], index[:count]
