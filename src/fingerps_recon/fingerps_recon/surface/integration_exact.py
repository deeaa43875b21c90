"""The ``EXACT`` solver of the masked Poisson equation A h = D^T g (:mod:`surface.integration`),
the reference: steps in float64, each connected component solved separately to a relative
residual of ``tol`` in float64 with a sparse matrix and a 2-D DCT preconditioner on the
component's rectangle (the pseudo-inverse of its Neumann Laplacian); a component that has
not converged after ``max_iter`` iterations (comb-like masks, long one-pixel tendrils:
nearly one-dimensional graphs) is solved by a sparse direct factorisation instead, and
components of fewer than ``_SMALL_COMPONENT`` pixels by one joint sparse direct solve.
"""

from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg

from fingerps_recon.errors import FingerpsReconError

_SMALL_COMPONENT = 2048


def solve_exact(
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
