"""The polynomial space of the FAST solver's start and last correction
(:mod:`surface.integration_fast`): the monomials s^a t^b, 1 <= a + b <= ``POLY_DEGREE`` (the
constant is free), in the box's coordinates s, t scaled to [-1, 1]. The start is the
polynomial closest to the solution in the A-norm, q0 = V c with V^T A V c = V^T b; the last
correction the one closest to the remaining error, V^T A V c = V^T r.

Here: their tables for a box (:func:`poly_tables`), a coefficient vector as a table
(:func:`coef_table`) and the inverse of the Gram matrix V^T A V (:func:`psd_inverse`); the
compiled passes are in :mod:`surface.integration_polynomial_kernel`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from fingerps_recon.surface import integration_polynomial_kernel as kernels

#: Degree of the polynomial space of the FAST solver's start and last correction.
POLY_DEGREE = kernels.POLY_DEGREE
# Its basis: monomials s^a t^b, 1 <= a + b <= POLY_DEGREE (the constant is free), as the
# pairs (BASIS_A[i], BASIS_B[i]).
_BASIS = [(a, t - a) for t in range(1, POLY_DEGREE + 1) for a in range(t + 1)]
BASIS_A = np.array([a for a, _ in _BASIS])
BASIS_B = np.array([b for _, b in _BASIS])


class PolyTables(NamedTuple):
    """Tables of the polynomial space on an h x w box (:func:`poly_tables`)."""

    col_powers: np.ndarray    # (D + 1, w) s(c)^a
    row_powers: np.ndarray    # (h, 2 D + 1) t(r)^k
    pair_prefix: np.ndarray   # (w, D * D) prefix sums over c of Dh_a(c) Dh_a'(c)
    power_prefix: np.ndarray  # (w + 1, 2 D + 1) prefix sums over c of s(c)^k
    row_steps: np.ndarray     # (h - 1, D * D) Dv_b(r) Dv_b'(r)


@lru_cache(maxsize=8)
def poly_tables(h: int, w: int) -> PolyTables:
    """Coordinates s = (c - (w - 1) / 2) / ((w - 1) / 2), t likewise for rows (in [-1, 1]),
    their powers, and the steps of the monomials along an edge: Dh_a(c) = s(c + 1)^a -
    s(c)^a (a = 1..D) between columns c and c + 1, Dv_b(r) likewise between rows
    (:func:`surface.integration_polynomial_kernel.poly_tables`); read-only, kept for the
    next bursts of the same box size."""
    deg = POLY_DEGREE
    tables = PolyTables(np.empty((deg + 1, w)), np.empty((h, 2 * deg + 1)),
                        np.empty((w, deg * deg)), np.empty((w + 1, 2 * deg + 1)),
                        np.empty((max(h - 1, 0), deg * deg)))
    kernels.poly_tables(*tables)
    for table in tables:
        table.setflags(write=False)
    return tables


def coef_table(coef: np.ndarray) -> np.ndarray:
    """(D + 1, D + 1) float64 table[a, b] of the polynomial
    sum_i coef[i] s^BASIS_A[i] t^BASIS_B[i]."""
    table = np.zeros((POLY_DEGREE + 1, POLY_DEGREE + 1))
    table[BASIS_A, BASIS_B] = coef
    return table


def psd_inverse(gram: np.ndarray) -> np.ndarray:
    """Inverse of the symmetric positive semi-definite ``gram``, or its pseudo-inverse
    (eigenvalues below 1e-12 of the largest count as zero) when it is singular: a mask too
    small or thin for some monomials."""
    inverse = np.empty_like(gram)
    if kernels.spd_inverse(gram, inverse):
        return inverse
    values, vectors = np.linalg.eigh(gram)
    keep = values > 1e-12 * max(values[-1], 0.0)
    return (vectors[:, keep] / values[keep]) @ vectors[:, keep].T
