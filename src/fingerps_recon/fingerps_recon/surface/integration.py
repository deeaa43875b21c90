"""Depth from normals by masked Poisson integration: the entry points, their checks and the
choice of solver.

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

``EXACT`` (the reference, :mod:`surface.integration_exact`): float64, each connected
component solved separately to a relative residual of ``tol`` (default ``EXACT_TOL`` = 1e-6)
with a sparse matrix and a 2-D DCT preconditioner on the component's rectangle, or by a
sparse direct factorisation where that does not converge (comb-like masks, long one-pixel
tendrils) and for the small components.

``FAST`` (the default, :mod:`surface.integration_fast`, which states its steps): float32, the
whole mask at once on its bounding box, in compiled loops. It starts from the polynomial of
low degree closest to the solution in the A-norm (:mod:`surface.integration_polynomials`),
iterates on the rest by conjugate gradients whose residual, after the first step, lives on
the mask's outline alone, with the rectangle's L^+ applied as DCTs along the rows and
tridiagonal solves down the columns (:mod:`surface.integration_preconditioner`), and ends
with the polynomial correction closest to the remaining error. Each iteration costs one
preconditioner application and one pass over the box. The residual ``tol`` (default
``FAST_TOL`` = 3e-3) is relative to |b|. On the simulated finger (172 000 pixels, bounding
box 432 x 459) that is 3 preconditioner applications, and FAST differs from ``EXACT`` by
~0.07 um RMS (depths spanning 5 mm), far below the error against the true surface (~1 um
from the true normals with the perspective model, 100-200 um with the orthographic one or
from Lambertian normals); ``tol`` = 1e-4 takes 5 and differs by ~0.015 um. Speed and
accuracy figures: ``bench/bench_recon_speed.py``. If it has not converged after
``min(max_iter, FAST_MAX_ITER)`` preconditioner applications (the comb-like masks ``EXACT``
solves directly) it falls back to ``EXACT``.

Each component is given zero mean height (its offset is not observable), so the whole result
has zero mean inside the mask.

Metric scale of points comes from the camera intrinsics and the working distance
(:mod:`surface.back_projection`): ``height_to_distance`` turns heights into distances along
the optical axis and ``depth_to_points`` back-projects them.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.mask_box import mask_bounding_box
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface.integration_exact import solve_exact
from fingerps_recon.surface.integration_fast import NON_FINITE, solve_fast
from fingerps_recon.surface.integration_steps import (
    Steps,
    log_depth_slopes,
    orthographic_slopes,
    orthographic_steps,
    perspective_steps,
)

#: Default relative residual of the FAST solver.
FAST_TOL = 3e-3
#: Iteration (preconditioner application) limit of the FAST solver before it falls back to
#: the EXACT one.
FAST_MAX_ITER = 30
#: Default relative residual of the EXACT solver.
EXACT_TOL = 1e-6


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
    _solve(orthographic_steps(n, box, min_nz=float(min_nz)), m, box, method=method, tol=tol,
           max_iter=max_iter, out=height, scale=pixel_size_m, offset=0.0, exponential=False,
           exact_steps=lambda: orthographic_slopes(n[box], m[box], min_nz=float(min_nz)))
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
        NaN outside the mask; ready for :func:`surface.back_projection.depth_to_points`.

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
    steps = perspective_steps(n, k, box, min_nz=float(min_nz))
    depth = _output(m.shape, box)
    _solve(steps, m, box, method=method, tol=tol, max_iter=max_iter, out=depth, scale=1.0,
           offset=float(np.log(working_distance_m)), exponential=True,
           exact_steps=lambda: log_depth_slopes(n, m, k, box, min_nz=float(min_nz)))
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


# ----------------------------------------------------------------------------- solvers


def _solve(
    steps: Steps,
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
    if method is IntegrationMethod.FAST and solve_fast(
        steps, mask, box, tol=FAST_TOL if tol is None else tol,
        max_iter=min(max_iter, FAST_MAX_ITER), out=out, scale=scale, offset=offset,
        exponential=exponential,
    ):
        return
    inside = mask[box]
    du, dv = exact_steps()
    values = solve_exact(du, dv, inside, tol=EXACT_TOL if tol is None else tol,
                         max_iter=max_iter)
    if not np.all(np.isfinite(values)):
        raise FingerpsReconError(NON_FINITE)
    view = out[box]
    view[...] = np.nan
    view[inside] = scale * values + offset
    if exponential:
        np.exp(view, out=view)


def warm_up() -> None:
    """Compile (or load) every kernel of the ``FAST`` solver (:mod:`surface.integration_fast`):
    a small mask of two components (only then does
    :func:`surface.integration_solution_kernel.finish_runs` run) integrated to a tight
    tolerance (several steps), with the dtypes a reconstruction gives."""
    v, u = np.mgrid[0:24, 0:30]
    mask = (np.hypot(u - 8, v - 12) < 6) | (np.hypot(u - 22, v - 12) < 5)
    normals = np.zeros((24, 30, 3), dtype=np.float32)
    normals[..., 0] = np.where(mask, (u - 15) / 40.0, 0.0)
    normals[..., 1] = np.where(mask, (v - 12) / 50.0, 0.0)
    normals[..., 2] = 1.0
    k = np.array([[3000.0, 0.0, 15.0], [0.0, 3000.0, 12.0], [0.0, 0.0, 1.0]])
    integrate_normals_perspective(normals, mask=mask, camera_matrix=k, working_distance_m=0.09,
                                  tol=1e-6)
