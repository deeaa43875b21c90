"""The FAST solver's preconditioner (:mod:`surface.integration_fast`): L^+, the pseudo-inverse
of the Neumann Laplacian L of the box (the discrete Frankot–Chellappa solver, diagonal in
the DCT-II basis; :mod:`surface.integration` says why it suits the masked equation).

It applies a DCT-II along the rows (pocketfft), a tridiagonal solve down each column
(Thomas' algorithm for T + mu_k I, mu_k = 2 - 2 cos(pi k / w2), the pivots kept per row
length; compiled: :func:`surface.integration_cg_kernel.neumann_columns`), the inverse DCT:
half the transforms of a 2-D DCT pair. Only the rows are rounded up to an FFT-friendly
length (the rectangle is otherwise the mask's bounding box: the less outside the mask, the
better the preconditioner). A sparse residual's row transform is summed directly from the
few outline pixels of each row (:func:`surface.integration_cg_kernel.outline_spectrum`,
from the table :func:`cosines`).
"""

from __future__ import annotations

import threading
from functools import lru_cache

import numpy as np
import scipy.fft

from fingerps_recon.surface.integration_cg_kernel import neumann_columns

# Threads for the DCTs of the FAST solver. Two (the machine's cores) gained nothing inside the
# solver: between DCTs pocketfft's second thread sleeps, and waking it cost about what it
# saved (more on a loaded machine); one thread leaves the other core to the rest of the node.
_FFT_WORKERS = 1


def precondition(buf: np.ndarray, pivots: tuple[np.ndarray, np.ndarray], *,
                transformed: bool = False) -> None:
    """buf = L^+ buf in place, L the Neumann Laplacian of the box (buf's shape): a DCT-II
    along the rows (unless ``transformed``: buf holds it already), a tridiagonal solve down
    each column (``pivots``: :func:`column_pivots` of the shape), the inverse DCT."""
    if not transformed:
        spec = scipy.fft.dct(buf, type=2, axis=1, norm="ortho", workers=_FFT_WORKERS,
                             overwrite_x=True)
        if spec.ctypes.data != buf.ctypes.data:  # pocketfft works in place; if it ever
            buf[...] = spec                      # does not
    neumann_columns(buf, *pivots)
    z = scipy.fft.idct(buf, type=2, axis=1, norm="ortho", workers=_FFT_WORKERS,
                       overwrite_x=True)
    if z.ctypes.data != buf.ctypes.data:
        buf[...] = z


@lru_cache(maxsize=4)
def cosines(w2: int) -> np.ndarray:
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
    next ones' 2 + mu: the last row of a box differs, :func:`column_pivots`). Kept per w2 and
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
def column_pivots(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
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
