"""The steps of the unknown per column (du) and per row (dv) from the normals: what the
least-squares integration (:mod:`surface.integration`, which derives them) integrates.

- Orthographic camera: the height's steps in pixels, du = p = -nx / nz and dv = -q = ny / nz
  (image rows run downwards), nz clamped from below by ``min_nz``.
- Pinhole camera: the log-depth's, dz~/du = nx / (fx D) and dz~/dv = -(ny + s nx / fx) / (fy D),
  D = nz - nx x_n + ny y_n clamped from below by ``min_nz`` |n| |r|.

The FAST solver computes them in float32 in its compiled pass from the arguments a
:class:`Steps` holds (:func:`perspective_steps`, :func:`orthographic_steps`); the EXACT
solver takes them as float64 arrays (:func:`orthographic_slopes`, :func:`log_depth_slopes`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


def orthographic_slopes(
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


class Steps(NamedTuple):
    """The arguments from which the FAST kernel computes each pixel's steps (du, dv): D =
    max(nz - nx x_n + ny y_n, min_nz |n| |r|), du = nx / (fx D),
    dv = -(ny + skew nx) / (fy D) (:func:`surface.integration_rhs_kernel.assemble_rhs`)."""

    normals: np.ndarray  # (H, W, 3) float32, C-contiguous
    x_n: np.ndarray      # (1, w) or (h, w) float32
    y_n: np.ndarray      # (h,) float32
    skew: np.float32
    min_nz: np.float32
    fx: np.float32
    fy: np.float32


def perspective_steps(
    normals: np.ndarray, camera_matrix: np.ndarray, box: tuple[slice, slice], *, min_nz: float
) -> Steps:
    """Steps of log depth per column and per row (module docstring) on ``box``."""
    fx, s, cx = (float(c) for c in camera_matrix[0])
    fy, cy = float(camera_matrix[1, 1]), float(camera_matrix[1, 2])
    rows, cols = box
    y_n = (np.arange(rows.start, rows.stop) - cy) / fy  # (h,)
    x_n = ((np.arange(cols.start, cols.stop) - cx) / fx)[None, :]  # (1, w), (h, w) with skew
    if s != 0.0:
        x_n = x_n - (s / fx) * y_n[:, None]
    f32 = np.float32
    return Steps(np.ascontiguousarray(normals, dtype=f32), x_n.astype(f32), y_n.astype(f32),
                 f32(s / fx), f32(min_nz), f32(fx), f32(fy))


def orthographic_steps(normals: np.ndarray, box: tuple[slice, slice], *,
                       min_nz: float) -> Steps:
    """Height steps in pixels per column and per row (module docstring) on ``box``: the
    perspective formula with x_n = y_n = 0 and fx = fy = -1, du = -nx / max(nz, min_nz |n|),
    dv = ny / max(nz, min_nz |n|)."""
    rows, cols = box
    f32 = np.float32
    return Steps(np.ascontiguousarray(normals, dtype=f32),
                 np.zeros((1, cols.stop - cols.start), dtype=f32),
                 np.zeros(rows.stop - rows.start, dtype=f32), f32(0.0), f32(min_nz),
                 f32(-1.0), f32(-1.0))


def log_depth_slopes(
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
