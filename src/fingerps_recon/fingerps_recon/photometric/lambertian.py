"""Lambertian photometric stereo (paper Eq. 3, NOTES §2): forward shading and the solver.

Per pixel, I_k = e_k * rho * max(0, l_k . n) for lights k with unit directions l_k (PS frame,
from the surface towards the light) and relative intensities e_k. With the rows of L scaled
by e_k, b = rho * n = (L^T L)^-1 L^T I over the lights that are usable at that pixel (not
in shadow, not saturated); rho = |b|, n = b / |b|.

The solve is one compiled per-pixel loop (:mod:`photometric.lambertian_kernel`, numba)
for distant lights (one direction per light) and near lights (a direction, and optionally an
intensity, per light and pixel) alike: each mask pixel accumulates its 3x3 normal equations
A b = L^T I, A = L^T L, over its usable lights and solves them in closed form (the adjugate
of A), in float32; the images are read as they are, inside the mask's bounding box only.
The same loop also gives each solved pixel's misfit to the model (for
:meth:`LambertianResult.relative_misfit`). Any number of lights >= 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric import lambertian_kernel
from fingerps_recon.photometric.kernel_threads import numba_threads
from fingerps_recon.photometric.light_intensities import checked_intensities
from fingerps_recon.photometric.mask_box import mask_bounding_box

# A pixel's (scaled) light directions are degenerate (e.g. coplanar) where
# det(A) <= this * (trace(A) / 3)**3, i.e. for A's eigenvalues (l, l, e) where e / l <= 3e-6
# (a smallest singular value of L below ~2e-3 of its largest): float32 normal equations
# cannot resolve less.
_MIN_RELATIVE_DETERMINANT = 1e-5
# Image dtypes the kernel reads directly (others are converted, see solve_lambertian).
_NATIVE_IMAGES = (np.uint8, np.uint16, np.float32, np.float64)
# Integer images reach the kernel as uint8 or uint16: values below this, exact in float32.
_INTEGER_LIMIT = 65536.0


def lambertian_shading(
    normals: np.ndarray, lights: np.ndarray, *, rho: np.ndarray | float
) -> np.ndarray:
    """Lambertian image formation rho * max(0, n . l) (paper Eq. 3).

    Parameters
    ----------
    normals : (..., 3) float
        Unit surface normals, PS frame.
    lights : (..., 3) float
        Unit directions from the surface towards the light, PS frame; broadcasts with
        ``normals`` (e.g. normals (H, W, 3), lights (K, 1, 1, 3) -> (K, H, W)).
    rho : (...) float or float
        Albedo (times light intensity), broadcasting with the result.

    Returns
    -------
    intensity : (...) float
        float32 if all array inputs are float32, else float64.
    """
    n = np.asarray(normals)
    lgt = np.asarray(lights)
    for name, arr in (("normals", n), ("lights", lgt)):
        if arr.ndim < 1 or arr.shape[-1] != 3:
            raise FingerpsReconError(f"{name} must have shape (..., 3), got {arr.shape}")
    try:
        np.broadcast_shapes(n.shape, lgt.shape)
    except ValueError:
        raise FingerpsReconError(
            f"normals {n.shape} and lights {lgt.shape} do not broadcast together; add "
            "singleton axes, e.g. lights[:, None, None, :]"
        ) from None
    rho_in = rho if isinstance(rho, (int, float)) else np.asarray(rho)
    dtype = np.result_type(n, lgt, rho_in, np.float32)
    cos = np.einsum("...k,...k->...", n.astype(dtype, copy=False), lgt.astype(dtype, copy=False))
    return (np.asarray(rho_in, dtype=dtype) * np.maximum(cos, 0)).astype(dtype, copy=False)


@dataclass(frozen=True)
class LambertianResult:
    """Result of :func:`solve_lambertian`.

    Attributes
    ----------
    normals : (H, W, 3) float32
        Unit normals in the PS frame; zeros where not ``valid``.
    albedo : (H, W) float32
        rho = |b| in image units per unit relative intensity; zero where not ``valid``.
    valid : (H, W) bool
        Pixels with at least 3 usable, non-degenerate lights and a non-zero solution.
    used_lights : (H, W) uint8 (uint16 for more than 255 lights)
        Number of lights used at each pixel (0 outside the mask).
    misfit_sq : float
        The Lambertian misfit of Eq. 3 summed over the ``valid`` pixels' used lights:
        sum (I_k - e_k rho max(0, n . l_k))^2, image units squared (float64 sum of
        float32 terms).
    observed_sum : float
        Sum of the ``valid`` pixels' used values I_k, image units.
    misfit_count : int
        Number of those values (the sum of ``used_lights`` over the ``valid`` pixels).
    """

    normals: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    used_lights: np.ndarray
    misfit_sq: float
    observed_sum: float
    misfit_count: int

    def relative_misfit(self) -> float | None:
        """rms(I - e rho max(0, n . l)) / mean(I) over the valid pixels' used values (Eq. 3's
        misfit, relative); None without such values or if their mean is not > 0."""
        if self.misfit_count == 0 or not self.observed_sum > 0:
            return None
        mean = self.observed_sum / self.misfit_count
        return math.sqrt(self.misfit_sq / self.misfit_count) / mean


@dataclass(frozen=True)
class LightRows:
    """The rows a_k = e_k l_k of the Lambertian system (Eq. 3) as the compiled solve reads
    them; made by :func:`light_rows`.

    Attributes
    ----------
    rows : (K, 3, H, W) or (K, 3, 1, 1) float32, C-contiguous, read-only
        x, y, z planes of a_k per light and pixel (near lights, or per-pixel intensities),
        or one a_k per light; NaN where light k is not usable at a pixel (its direction or
        intensity not finite, or its intensity not > 0).
    """

    rows: np.ndarray

    @property
    def light_count(self) -> int:
        return int(self.rows.shape[0])


def light_rows(
    lights: np.ndarray,
    *,
    shape: tuple[int, int],
    intensities: np.ndarray | None = None,
) -> LightRows:
    """The rows a_k = e_k l_k of :func:`solve_lambertian`'s system for images of ``shape``.

    Parameters
    ----------
    lights : (K, 3) or (K, H, W, 3) float
        As :func:`solve_lambertian`.
    shape : (H, W)
        The images' size.
    intensities : (K,) or (K, H, W) float, optional
        As :func:`solve_lambertian`.

    Raises
    ------
    FingerpsReconError
        As :func:`solve_lambertian`, for the lights and intensities.
    """
    h, w = (int(v) for v in shape)
    lgt = np.asarray(lights)
    k = lgt.shape[0] if lgt.ndim in (2, 4) else 0
    if lgt.shape not in ((k, 3), (k, h, w, 3)):
        raise FingerpsReconError(
            f"lights must have shape (K, 3) or (K, H, W, 3) = (K, {h}, {w}, 3) to match "
            f"images of {h} x {w} px, got {lgt.shape}"
        )
    if k < 3:
        raise FingerpsReconError(f"photometric stereo needs at least 3 lights, got {k}")
    if lgt.ndim == 2 and not np.all(np.isfinite(lgt)):
        raise FingerpsReconError("lights contain non-finite values; check the calibration")
    e = checked_intensities(intensities, shape=(k, h, w))
    if lgt.ndim == 2 and e.ndim == 1:
        rows = (lgt * e[:, None]).astype(np.float32).reshape(k, 3, 1, 1)
    else:
        rows = np.empty((k, 3, h, w), dtype=np.float32)
        with np.errstate(invalid="ignore", over="ignore"):
            for i in range(k):  # one light at a time: planes, no (K, H, W, 3) temporary
                e_i = np.asarray(e[i], dtype=np.float32)
                for c in range(3):
                    np.multiply(lgt[i, ..., c], e_i, out=rows[i, c], casting="unsafe")
                if e_i.ndim:
                    rows[i][:, ~((e_i > 0) & (e_i < np.inf))] = np.nan
    rows.setflags(write=False)
    return LightRows(rows)


def solve_lambertian(
    images: np.ndarray,
    lights: np.ndarray | LightRows,
    *,
    intensities: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    shadow_level: float = 0.0,
    saturation_level: float | None = None,
) -> LambertianResult:
    """Least-squares Lambertian photometric stereo with per-pixel light selection (Eq. 3).

    At each pixel the lights whose value is <= ``shadow_level`` (attached or cast shadow)
    or >= ``saturation_level`` (clipped), or not finite, are left out, and so is a light
    whose direction or intensity at that pixel is not finite or whose intensity is not > 0;
    the rest, a_k = e_k l_k (:func:`light_rows`), give b = rho n = A^-1 sum_k a_k I_k,
    A = sum_k a_k a_k^T (the least-squares solution pinv(L_used) I_used). Pixels with fewer
    than 3 usable lights, or whose usable lights are degenerate (nearly coplanar
    directions), are marked invalid rather than guessed. The sign of n_z is not forced.
    Float32 arithmetic; distant and near lights go through the same compiled loop
    (:mod:`photometric.lambertian_kernel`), in at most two threads, over the mask's
    bounding box only.

    Parameters
    ----------
    images : (K, H, W) float or int
        One image per light, any linear scale (flat-field corrected, dark-subtracted).
        uint8, uint16, float32 and float64 are read as they are; other integer and float
        dtypes are converted first (float32 where exact, else float64).
    lights : (K, 3) or (K, H, W, 3) float, or LightRows
        Unit directions from the surface towards each light, PS frame: one per light, or one
        per light and pixel (near lights, e.g. from the LED positions and a depth estimate);
        or the rows a_k = e_k l_k made from them by :func:`light_rows` (then no
        ``intensities``).
    intensities : (K,) or (K, H, W) float, optional
        Relative light intensities e_k > 0, scaling the rows of L (per pixel: the near-light
        irradiance); default all ones.
    mask : (H, W) bool, optional
        Pixels to solve; the rest are invalid. Default: all.
    shadow_level : float
        Values <= this are treated as shadowed, in image units. Default 0.
    saturation_level : float, optional
        Values >= this are treated as saturated. Default: no saturation test.

    Returns
    -------
    LambertianResult

    Raises
    ------
    FingerpsReconError
        On inconsistent shapes, fewer than 3 lights, images that are not real numbers, or
        non-finite or non-positive (K,) intensities or non-finite (K, 3) lights.
    """
    imgs = np.asarray(images)
    if imgs.ndim != 3:
        raise FingerpsReconError(f"images must have shape (K, H, W), got {imgs.shape}")
    k, h, w = imgs.shape
    if imgs.dtype.kind not in "biuf":
        raise FingerpsReconError(
            f"images must be integers or floats, got dtype {imgs.dtype}; convert them first")
    if isinstance(lights, LightRows):
        if intensities is not None:
            raise FingerpsReconError(
                "light rows already hold the intensities: give no intensities with them")
        prepared = lights
        if (prepared.rows.shape[0] != k
                or prepared.rows.shape[2:] not in ((1, 1), (h, w))):
            raise FingerpsReconError(
                f"light rows {prepared.rows.shape} do not fit the images {imgs.shape}")
    else:
        lgt = np.asarray(lights)
        if lgt.shape not in ((k, 3), (k, h, w, 3)):
            raise FingerpsReconError(
                f"lights must have shape (K, 3) = ({k}, 3) or (K, H, W, 3) = ({k}, {h}, {w}, 3) "
                f"to match images {imgs.shape}, got {lgt.shape}"
            )
        prepared = light_rows(lgt, shape=(h, w), intensities=intensities)
    if mask is None:
        m = np.ones((h, w), dtype=bool)
    else:
        m = np.ascontiguousarray(mask)
        if m.shape != (h, w) or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape (H, W) = ({h}, {w}), got {m.shape} {m.dtype}"
            )
    box = mask_bounding_box(m)

    normals = np.zeros((h, w, 3), dtype=np.float32)
    albedo = np.zeros((h, w), dtype=np.float32)
    valid = np.zeros((h, w), dtype=bool)
    used = np.zeros((h, w), dtype=np.uint8 if k <= np.iinfo(np.uint8).max else np.uint16)
    sums = (0.0, 0.0, 0)
    if box is not None:
        values = _kernel_images(imgs)
        lo, hi = _levels(values.dtype, shadow_level, saturation_level)
        rows, cols = box
        chunks = (rows.stop - rows.start) * -(-(cols.stop - cols.start) // lambertian_kernel.CHUNK)
        parts = np.zeros((chunks, 3))
        with numba_threads():
            lambertian_kernel.solve(
                values, prepared.rows, m,
                np.array((rows.start, rows.stop, cols.start, cols.stop), dtype=np.int64), lo, hi,
                np.float32(_MIN_RELATIVE_DETERMINANT),
                normals, albedo, valid, used, parts,
            )
        total = parts.sum(axis=0)  # in chunk order: the same whatever the threads
        sums = (float(total[0]), float(total[1]), int(total[2]))
    return LambertianResult(normals=normals, albedo=albedo, valid=valid, used_lights=used,
                            misfit_sq=sums[0], observed_sum=sums[1], misfit_count=sums[2])


def _kernel_images(images: np.ndarray) -> np.ndarray:
    """The images as the kernel reads them: uint8, uint16, float32 and float64 as they are
    (C-contiguous), other dtypes converted (float32 where exact, else float64)."""
    if images.dtype in _NATIVE_IMAGES:
        return np.ascontiguousarray(images)
    exact = images.dtype.kind == "b" or images.dtype.itemsize <= 2
    return images.astype(np.float32 if exact else np.float64)


def _levels(
    dtype: np.dtype, shadow_level: float, saturation_level: float | None
) -> tuple[np.floating, np.floating]:
    """The shadow and saturation levels as the kernel compares them with values of ``dtype``,
    exactly as real numbers, as float32 (the kernel's loops then compare in float32 lanes):
    for float32 values the float32 that splits them the same way; for the integer values
    (uint8, uint16) the integer that does (v > lo iff v > floor(lo), v < hi iff
    v < ceil(hi)), held within [-1, 65536], where float32 is exact; float64 for float64
    values. No saturation level is +inf (which also leaves out infinite values)."""
    if dtype == np.float32:
        lo = _float32_threshold(shadow_level, above=True)
        hi = (np.float32(np.inf) if saturation_level is None
              else _float32_threshold(saturation_level, above=False))
        return lo, hi
    hi = np.inf if saturation_level is None else saturation_level
    if dtype.kind in "ui":
        return (np.float32(np.clip(np.floor(shadow_level), -1.0, _INTEGER_LIMIT)),
                np.float32(np.clip(np.ceil(hi), -1.0, _INTEGER_LIMIT)))
    return np.float64(shadow_level), np.float64(hi)


def _float32_threshold(level: float, *, above: bool) -> np.float32:
    """t with (v > t) == (v > level) (above) or (v < t) == (v < level), for float32 v."""
    with np.errstate(over="ignore"):
        t = np.float32(level)
    if above and float(t) > level:
        t = np.nextafter(t, np.float32(-np.inf))
    elif not above and float(t) < level:
        t = np.nextafter(t, np.float32(np.inf))
    return t
