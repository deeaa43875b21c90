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
Both solve that same masked system by conjugate gradients preconditioned with the exact
inverse of the Laplacian of a bounding *rectangle*, applied by a DCT-II (the discrete
Frankot–Chellappa / Neumann Poisson solver): the residual is extended by zero to the
rectangle, solved there and restricted back. This fictitious-domain preconditioner suits a
Neumann problem: for a compact, fingertip-like mask the iteration count hardly grows with its
size. The first iteration *is* the Frankot–Chellappa solution on the bounding box with the
gradients outside the mask set to zero; the rest correct it for the mask's shape, whose
effect is a smooth (discrete harmonic) correction driven from the mask's outline.

``EXACT`` (the reference): each connected component is solved separately to a relative
residual of ``tol`` (default 1e-6) in float64 with a sparse matrix; a component that has not
converged after ``max_iter`` iterations (comb-like masks, long one-pixel tendrils: nearly
one-dimensional graphs) is solved by a sparse direct factorisation instead, and components of
fewer than ``_SMALL_COMPONENT`` pixels by one joint sparse direct solve. About 130 ms for the
simulated finger (172 000 pixels) on the two-core machine, most of it sparse-matrix set-up and
gathers.

``FAST`` (the default): the whole mask at once on its bounding box (the box's sides rounded
up to FFT-friendly lengths), in float32, with the Laplacian applied as a 4-neighbour stencil
(``cv2.filter2D``) instead of a sparse matrix, to a relative residual of ``tol`` (default
``FAST_TOL`` = 1e-4). The mean steps (a tilted plane, which satisfies every edge equation
exactly) are taken out first and added back at the end, so a plane costs no iteration and the
Frankot–Chellappa start is closer. Per iteration: one stencil product and one DCT pair of the
box. On the simulated finger (bounding box 432 x 459, padded to 432 x 480) it takes 4
iterations after the start, ~20 ms on the busy two-core machine (EXACT: 130-160 ms; about
8 ms of it are the 5 DCT pairs), and differs from ``EXACT`` by ~0.03 um RMS (heights
spanning 5 mm), far below the error against the true surface (~1 um from the true normals
with the perspective model, 100-200 um with the orthographic one or from Lambertian
normals); measurements in ``bench/bench_recon_speed.py``. A looser ``tol`` = 1e-3 saves
one DCT pair and still differs by only ~0.2 um RMS. If it has not converged after
``min(max_iter, FAST_MAX_ITER)`` iterations (the comb-like masks ``EXACT`` solves directly)
it falls back to ``EXACT``.

Each component is given zero mean height (its offset is not observable), so the whole result
has zero mean inside the mask.

Metric scale of points comes from the camera intrinsics and the working distance:
:func:`height_to_distance` turns heights into distances along the optical axis and
:func:`depth_to_points` back-projects them.
"""

from __future__ import annotations

from enum import Enum
from functools import lru_cache

import cv2
import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.mask_box import mask_bounding_box
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface.integration_kernel import log_depth_steps

_SMALL_COMPONENT = 2048

#: Default relative residual of the FAST solver.
FAST_TOL = 1e-4
#: Iteration limit of the FAST solver before it falls back to the EXACT one.
FAST_MAX_ITER = 30
#: Default relative residual of the EXACT solver.
EXACT_TOL = 1e-6

# Threads for the DCTs of the FAST solver. Two (the machine's cores) gained nothing inside the
# solver: between DCTs pocketfft's second thread sleeps, and waking it cost about what it
# saved on a 432 x 480 DCT (~0.8 ms); one thread leaves the other core to the rest of the node.
_FFT_WORKERS = 1
_CROSS = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=np.float32)
_MINUS_CROSS = -_CROSS


class IntegrationMethod(Enum):
    """Solver of the masked Poisson equation (see the module docstring)."""

    FAST = "fast"
    """Bounding-box PCG in float32 with stencil products, to ``FAST_TOL``; the default."""
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
        ``FAST_TOL`` (1e-5) or ``EXACT_TOL`` (1e-6) by ``method``.
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
    height = np.full(m.shape, np.nan, dtype=np.float32)
    box = mask_bounding_box(m)
    if box is None:
        return height
    nb, mb = n[box], m[box]
    if method is IntegrationMethod.EXACT:
        du, dv = _slopes(nb, mb, min_nz=float(min_nz))
    else:
        du, dv = _slopes_f32(nb, mb, min_nz=float(min_nz))
    solution = _solve(du, dv, mb, method=method, tol=tol, max_iter=max_iter)
    height[box] = solution * pixel_size_m
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
    depth = np.full(m.shape, np.nan, dtype=np.float32)
    box = mask_bounding_box(m)
    if box is None:
        return depth
    du, dv = _log_depth_steps(n, m, k, box, min_nz=float(min_nz))
    if method is IntegrationMethod.EXACT:
        du, dv = du.astype(np.float64), dv.astype(np.float64)
    log_depth = _solve(du, dv, m[box], method=method, tol=tol, max_iter=max_iter)
    log_depth += np.log(working_distance_m).astype(log_depth.dtype)
    depth[box] = np.exp(log_depth)
    return depth


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
    m = np.asarray(mask)
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


def _components_f32(
    normals: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """nx, ny, nz (float32 planes, not normalised), |n| and the usable pixels.

    Usable: inside the mask, finite and non-zero.
    """
    if normals.dtype != np.float32:
        normals = normals.astype(np.float32)
    nx, ny, nz = cv2.split(normals)  # contiguous planes
    norm = nx * nx
    norm += ny * ny
    norm += nz * nz
    np.sqrt(norm, out=norm)
    with np.errstate(invalid="ignore"):
        usable = (norm > 0) & (norm < np.inf)  # NaN compares False
    usable &= mask
    return nx, ny, nz, norm, usable


def _slopes_f32(
    normals: np.ndarray, mask: np.ndarray, *, min_nz: float
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`_slopes` in float32: -nx / max(nz, min_nz |n|) needs no normalisation."""
    nx, ny, nz, norm, usable = _components_f32(normals, mask)
    norm *= np.float32(min_nz)
    np.maximum(nz, norm, out=norm)
    return _divided(-nx, ny, norm, usable)


def _divided(
    num_u: np.ndarray, num_v: np.ndarray, den: np.ndarray, usable: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """num_u / den and num_v / den where usable, else 0 (float32)."""
    inv = np.divide(np.float32(1.0), den, out=np.zeros_like(den), where=usable)
    du = np.multiply(num_u, inv, out=np.zeros_like(inv), where=usable)
    dv = np.multiply(num_v, inv, out=inv, where=usable)
    return du, dv


def _log_depth_steps(
    normals: np.ndarray,
    mask: np.ndarray,
    camera_matrix: np.ndarray,
    box: tuple[slice, slice],
    *,
    min_nz: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Steps of log depth per column and per row (module docstring), float32, on ``box``
    of the (H, W, 3) ``normals`` and (H, W) ``mask``: one compiled pass
    (:func:`surface.integration_kernel.log_depth_steps`)."""
    fx, s, cx = (float(c) for c in camera_matrix[0])
    fy, cy = float(camera_matrix[1, 1]), float(camera_matrix[1, 2])
    rows, cols = box
    h, w = rows.stop - rows.start, cols.stop - cols.start
    y_n = (np.arange(rows.start, rows.stop) - cy) / fy  # (h,)
    x_n = ((np.arange(cols.start, cols.stop) - cx) / fx)[None, :]  # (1, w), (h, w) with skew
    if s != 0.0:
        x_n = x_n - (s / fx) * y_n[:, None]
    du = np.empty((h, w), dtype=np.float32)
    dv = np.empty((h, w), dtype=np.float32)
    f32 = np.float32
    log_depth_steps(np.ascontiguousarray(normals, dtype=f32), np.ascontiguousarray(mask),
                    rows.start, cols.start, x_n.astype(f32), y_n.astype(f32), f32(s / fx),
                    f32(min_nz), f32(fx), f32(fy), du, dv)
    return du, dv


# ----------------------------------------------------------------------------- solvers


def _solve(
    du: np.ndarray,
    dv: np.ndarray,
    mask: np.ndarray,
    *,
    method: IntegrationMethod,
    tol: float | None,
    max_iter: int,
) -> np.ndarray:
    """Least-squares integration of the steps over ``mask``; (h, w), NaN outside.

    float32 from ``FAST``, float64 from ``EXACT`` (or the fallback to it).
    """
    solution = None
    if method is IntegrationMethod.FAST:
        solution = _solve_fast(
            du,
            dv,
            mask,
            tol=FAST_TOL if tol is None else tol,
            max_iter=min(max_iter, FAST_MAX_ITER),
        )
    if solution is None:  # EXACT, or FAST did not converge
        values = _solve_exact(
            du.astype(np.float64, copy=False),
            dv.astype(np.float64, copy=False),
            mask,
            tol=EXACT_TOL if tol is None else tol,
            max_iter=max_iter,
        )
        solution = np.full(mask.shape, np.nan)
        solution[mask] = values
    if not np.all(np.isfinite(solution[mask])):
        raise FingerpsReconError(
            "normal integration produced non-finite values; check that the normals inside "
            "the mask are finite"
        )
    return solution


def _solve_fast(
    du: np.ndarray, dv: np.ndarray, mask: np.ndarray, *, tol: float, max_iter: int
) -> np.ndarray | None:
    """Masked Poisson solve on the mask's bounding box (module docstring, ``FAST``).

    Parameters
    ----------
    du, dv : (h, w) float32
        Steps per column and per row, zero outside ``mask``.
    mask : (h, w) bool

    Returns
    -------
    solution : (h, w) float32 or None
        Zero mean per 4-connected component of the mask, NaN outside; None if the relative
        residual is still above ``tol`` after ``max_iter`` iterations.
    """
    h, w = mask.shape
    shape = (
        scipy.fft.next_fast_len(h, real=True),
        scipy.fft.next_fast_len(w, real=True),
    )
    inside = np.zeros(shape, dtype=np.float32)
    inside[:h, :w] = mask
    labels, n_comp = _labels(mask)
    # The mean steps are a plane, which every edge equation satisfies exactly: integrate
    # only the rest, whose smaller values at the mask's outline the Frankot–Chellappa start
    # (zero steps outside the mask) matches better; a tilted plane needs no iteration at all.
    n_pix = np.count_nonzero(mask)
    mean_du = np.float32(du.sum(dtype=np.float64) / n_pix)
    mean_dv = np.float32(dv.sum(dtype=np.float64) / n_pix)

    # b = D^T g over the edges with both ends inside, g = mean of the two pixels' steps less
    # the plane's (du, dv are zero outside the mask, so g is only used on such edges).
    b = np.zeros(shape, dtype=np.float32)
    g = du[:, :-1] + du[:, 1:]
    g *= np.float32(0.5)
    g -= mean_du
    g *= inside[:h, : w - 1]
    g *= inside[:h, 1:w]
    b[:h, 1:w] += g
    b[:h, : w - 1] -= g
    g = dv[:-1] + dv[1:]
    g *= np.float32(0.5)
    g -= mean_dv
    g *= inside[: h - 1, :w]
    g *= inside[1:h, :w]
    b[1:h, :w] += g
    b[: h - 1, :w] -= g
    # Each component's sum of b is zero in exact arithmetic; remove the round-off.
    _subtract_component_means(b[:h, :w], mask, labels, n_comp)

    x = _pcg_box(b, inside, tol=tol, max_iter=max_iter)
    if x is None:
        return None
    solution = x[:h, :w]
    solution += mean_du * np.arange(w, dtype=np.float32)
    solution += mean_dv * np.arange(h, dtype=np.float32)[:, None]
    _subtract_component_means(solution, mask, labels, n_comp)
    solution[~mask] = np.nan
    return solution


def _pcg_box(
    b: np.ndarray, inside: np.ndarray, *, tol: float, max_iter: int
) -> np.ndarray | None:
    """Solve A x = b for the masked graph Laplacian A of ``inside`` on its whole box.

    Conjugate gradients preconditioned by the box's Neumann Laplacian (DCT-II), all float32,
    A applied as a 4-neighbour stencil. ``b`` and the result are zero outside the mask.
    Returns None if the relative residual is above ``tol`` after ``max_iter`` iterations.
    """
    shape = b.shape
    x = np.zeros(shape, dtype=np.float32)
    b_norm2 = float(np.vdot(b, b))
    if b_norm2 == 0.0:
        return x
    degree = cv2.filter2D(inside, -1, _CROSS, borderType=cv2.BORDER_CONSTANT)
    degree *= inside

    def laplacian(v: np.ndarray) -> np.ndarray:
        # degree * v - (sum of the inside neighbours), v zero outside: three passes
        av = cv2.filter2D(v, -1, _MINUS_CROSS, borderType=cv2.BORDER_CONSTANT)
        av *= inside
        cv2.accumulateProduct(degree, v, av)
        return av

    inv_ev = _inverse_eigenvalues(shape)

    def precondition(res: np.ndarray) -> np.ndarray:
        spec = scipy.fft.dctn(res, type=2, norm="ortho", workers=_FFT_WORKERS)
        spec *= inv_ev
        z = scipy.fft.idctn(spec, type=2, norm="ortho", workers=_FFT_WORKERS, overwrite_x=True)
        z *= inside
        return z

    # From x = 0 the first step is Frankot–Chellappa on the box (zero steps outside).
    limit = tol * tol * b_norm2
    r = b
    z = precondition(r)
    d = z
    rz = float(np.vdot(r, z))
    for _ in range(max_iter):
        ad = laplacian(d)
        alpha = rz / float(np.vdot(d, ad))
        x = cv2.scaleAdd(d, alpha, x)  # x + alpha d, one pass
        r = cv2.scaleAdd(ad, -alpha, r)
        if float(np.vdot(r, r)) <= limit:
            return x
        z = precondition(r)
        rz_new = float(np.vdot(r, z))
        d = cv2.scaleAdd(d, rz_new / rz, z)
        rz = rz_new
    return None


@lru_cache(maxsize=4)
def _inverse_eigenvalues(shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 inverse eigenvalues of the h x w rectangle's 4-neighbour Neumann
    Laplacian in the DCT-II basis, 0 for the constant mode (free); read-only, kept for the
    next burst of the same box size."""
    ev = (2.0 - 2.0 * np.cos(np.pi * np.arange(shape[0]) / shape[0]))[:, None] + (
        2.0 - 2.0 * np.cos(np.pi * np.arange(shape[1]) / shape[1])
    )[None, :]
    ev[0, 0] = 1.0
    inv_ev = (1.0 / ev).astype(np.float32)
    inv_ev[0, 0] = 0.0  # the constant mode is free
    inv_ev.setflags(write=False)
    return inv_ev


def _labels(mask: np.ndarray) -> tuple[np.ndarray | None, int]:
    """4-connected component labels 0..n-1 of the mask pixels (None if there is one)."""
    n_labels, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=4)
    if n_labels <= 2:
        return None, 1
    return labels[mask] - 1, n_labels - 1


def _subtract_component_means(
    values: np.ndarray, mask: np.ndarray, labels: np.ndarray | None, n_comp: int
) -> None:
    """Give ``values`` (in place) zero mean over the mask pixels of each component.

    Values outside the mask are left as they are.
    """
    if labels is None:  # one pass for the mean, one for the subtraction (OpenCV, masked)
        inside = mask.view(np.uint8)
        mean = cv2.mean(values, mask=inside)[0]
        cv2.subtract(values, mean, dst=values, mask=inside)
        return
    inner = values[mask]
    sums = np.bincount(labels, weights=inner, minlength=n_comp)
    counts = np.bincount(labels, minlength=n_comp)
    inner -= (sums / counts).astype(np.float32)[labels]
    values[mask] = inner


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
    h, w = depth.shape
    keep = np.zeros((h, w), dtype=bool)
    box = mask_bounding_box(m)
    if box is None:
        return np.empty((0, 3), dtype=np.float32), np.empty(0, dtype=np.int64)
    # Everything on the mask's bounding box only: planes there, then one gather each
    # (raster order in the box is raster order in the image).
    z = depth[box].astype(np.float32, copy=False)
    with np.errstate(invalid="ignore"):
        kept = m[box] & (z > 0) & (z < np.inf)  # NaN compares False
    keep[box] = kept
    index = np.flatnonzero(keep)
    rows, cols = box
    y_row = ((np.arange(rows.start, rows.stop) - cy) / fy).astype(np.float32)[:, None]  # y_n
    x_col = ((np.arange(cols.start, cols.stop) - cx) / fx).astype(np.float32)  # x_n, no skew
    points = np.empty((index.size, 3), dtype=np.float32)
    y = z * y_row
    points[:, 1] = y[kept]
    x = z * x_col
    if s != 0.0:
        x -= np.float32(s / fx) * y
    points[:, 0] = x[kept]
    points[:, 2] = z[kept]
    return points, index.astype(np.int64, copy=False)
