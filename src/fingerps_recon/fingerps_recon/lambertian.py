"""Lambertian photometric stereo (paper Eq. 3, NOTES §2): forward shading and the solver.

Per pixel, I_k = e_k * rho * max(0, l_k . n) for lights k with unit directions l_k (PS frame,
from the surface towards the light) and relative intensities e_k. With the rows of L scaled
by e_k, b = rho * n = (L^T L)^-1 L^T I over the lights that are usable at that pixel (not
in shadow, not saturated); rho = |b|, n = b / |b|.

Distant lights (one L for the whole image): the pixels where every light is usable share one
pseudo-inverse, applied as one float32 product; only the minority with shadowed or saturated
lights (the finger's margins) is grouped by its pattern of usable lights. Near lights (a
direction, and optionally an intensity, per pixel): each pixel's 3x3 normal equations
A b = L^T I, A = L^T L, are accumulated over the usable lights and solved in closed form by
the cofactors of A, vectorised over the pixels. Both work on the mask's bounding box only.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .errors import FingerpsReconError

# Smallest singular value of the used (scaled) light matrix, relative to its largest, below
# which a pixel's light subset is treated as degenerate (e.g. coplanar light directions).
_MIN_RELATIVE_SINGULAR_VALUE = 1e-6
# The same for per-pixel lights, whose float32 normal equations cannot resolve 1e-6: a pixel
# is degenerate where det(A) <= this * (trace(A) / 3)**3, i.e. for A's eigenvalues
# (l, l, e) where e / l <= 3e-6 (a smallest singular value of L below ~2e-3 of its largest).
_MIN_RELATIVE_DETERMINANT = 1e-5

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
    used_lights : (H, W) uint8
        Number of lights used at each pixel (0 outside the mask).
    """

    normals: np.ndarray
    albedo: np.ndarray
    valid: np.ndarray
    used_lights: np.ndarray


def solve_lambertian(
    images: np.ndarray,
    lights: np.ndarray,
    *,
    intensities: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    shadow_level: float = 0.0,
    saturation_level: float | None = None,
) -> LambertianResult:
    """Least-squares Lambertian photometric stereo with per-pixel light selection (Eq. 3).

    At each pixel the lights whose value is <= ``shadow_level`` (attached or cast shadow)
    or >= ``saturation_level`` (clipped), or not finite, are left out; the rest give
    b = rho n = pinv(L_used) I_used. Pixels with fewer than 3 usable lights, or whose usable
    lights are degenerate (coplanar directions), are marked invalid rather than guessed. The
    sign of n_z is not forced.

    Distant lights, ``lights`` (K, 3): the pixels with every light usable are solved by one
    float32 product with the precomputed pseudo-inverse of L; the others are grouped by
    their pattern of usable lights (at most 2^K groups, in practice a few dozen) and each
    group is solved with one pseudo-inverse (float64). Near lights, ``lights`` (K, H, W, 3)
    or ``intensities`` (K, H, W): each pixel solves its 3x3 normal equations over its usable
    lights in closed form (float32); a light whose direction or intensity is not finite, or
    whose intensity is not > 0, at a pixel is left out there.

    Parameters
    ----------
    images : (K, H, W) float or int
        One image per light, any linear scale (flat-field corrected, dark-subtracted).
    lights : (K, 3) or (K, H, W, 3) float
        Unit directions from the surface towards each light, PS frame: one per light, or one
        per light and pixel (near lights, e.g. from the LED positions and a depth estimate).
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
        On inconsistent shapes, fewer than 3 lights, or non-finite or non-positive (K,)
        intensities or non-finite (K, 3) lights.
    """
    imgs = np.asarray(images)
    if imgs.ndim != 3:
        raise FingerpsReconError(f"images must have shape (K, H, W), got {imgs.shape}")
    k, h, w = imgs.shape
    lgt = np.asarray(lights)
    if lgt.shape not in ((k, 3), (k, h, w, 3)):
        raise FingerpsReconError(
            f"lights must have shape (K, 3) = ({k}, 3) or (K, H, W, 3) = ({k}, {h}, {w}, 3) "
            f"to match images {imgs.shape}, got {lgt.shape}"
        )
    if k < 3:
        raise FingerpsReconError(f"photometric stereo needs at least 3 lights, got {k}")
    if k > 62:
        raise FingerpsReconError(f"at most 62 lights are supported, got {k}")
    if lgt.ndim == 2 and not np.all(np.isfinite(lgt)):
        raise FingerpsReconError("lights contain non-finite values; check the calibration")
    if intensities is None:
        e = np.ones(k)
    else:
        e = np.asarray(intensities)
        if e.shape not in ((k,), (k, h, w)):
            raise FingerpsReconError(
                f"intensities must have shape (K,) = ({k},) or (K, H, W) = ({k}, {h}, {w}), "
                f"got {e.shape}"
            )
        if e.ndim == 1 and not np.all(np.isfinite(e) & (e > 0)):
            raise FingerpsReconError(f"intensities must be finite and > 0, got {e}")
    if mask is None:
        box = (slice(0, h), slice(0, w))
        m = None
    else:
        m = np.asarray(mask)
        if m.shape != (h, w) or m.dtype != bool:
            raise FingerpsReconError(
                f"mask must be a bool array of shape (H, W) = ({h}, {w}), got {m.shape} {m.dtype}"
            )
        box = _bounding_box(m)

    normals = np.zeros((h, w, 3), dtype=np.float32)
    albedo = np.zeros((h, w), dtype=np.float32)
    valid = np.zeros((h, w), dtype=bool)
    used = np.zeros((h, w), dtype=np.uint8)
    if box is not None:
        values = imgs[:, box[0], box[1]].astype(np.float32)  # (K, h, w), a copy
        usable = _usable_lights(
            values if _exact_in_float32(imgs.dtype) else imgs[:, box[0], box[1]],
            None if m is None else m[box],
            shadow_level=shadow_level,
            saturation_level=saturation_level,
        )
        code = _light_code(usable)
        count = np.bitwise_count(code)
        if lgt.ndim == 2 and e.ndim == 1:
            scaled = lgt.astype(np.float64) * e.astype(np.float64)[:, None]
            b, solved = _solve_distant(values, scaled, usable, code, count)
        else:
            b, solved = _solve_per_pixel(values, lgt, e, usable, count, box)
        rho = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
        with np.errstate(invalid="ignore"):
            ok = solved & (rho > 0) & (rho < np.inf)  # NaN compares False
        inv_rho = np.divide(np.float32(1.0), rho, out=np.zeros_like(rho), where=ok)
        unit = np.zeros_like(b)
        np.multiply(b, inv_rho, out=unit, where=ok)
        normals[box] = cv2.merge(list(unit))  # interleave the planes: (h, w, 3)
        np.copyto(albedo[box], rho, where=ok)
        valid[box] = ok
        used[box] = count
    return LambertianResult(normals=normals, albedo=albedo, valid=valid, used_lights=used)


def _bounding_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """Slices of the smallest rectangle holding every mask pixel; None for an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0] : rows[-1] + 1].any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def _exact_in_float32(dtype: np.dtype) -> bool:
    """Whether every value of ``dtype`` converts to float32 exactly."""
    return dtype == np.bool_ or dtype in (np.uint8, np.int8, np.uint16, np.int16) or (
        dtype.kind == "f" and dtype.itemsize <= 4
    )


def _usable_lights(
    values: np.ndarray,
    mask: np.ndarray | None,
    *,
    shadow_level: float,
    saturation_level: float | None,
) -> np.ndarray:
    """(K, h, w) bool: inside ``mask``, above the shadow and below the saturation level.

    The thresholds are applied exactly as real numbers to the values as given: for float32
    values they are first moved to the float32 that splits the values the same way.
    """
    if values.dtype == np.float32:
        lo = _float32_threshold(shadow_level, above=True)
        hi = None if saturation_level is None else _float32_threshold(saturation_level, above=False)
    else:
        lo = np.float64(shadow_level)
        hi = None if saturation_level is None else np.float64(saturation_level)
    with np.errstate(invalid="ignore"):
        usable = values > lo  # NaN compares False
        if hi is not None:
            usable &= values < hi
        elif values.dtype.kind in "fc":
            usable &= values < np.inf
    if mask is not None:
        usable &= mask
    return usable


def _float32_threshold(level: float, *, above: bool) -> np.float32:
    """t with (v > t) == (v > level) (above) or (v < t) == (v < level), for float32 v."""
    t = np.float32(level)
    if above and float(t) > level:
        t = np.nextafter(t, np.float32(-np.inf))
    elif not above and float(t) < level:
        t = np.nextafter(t, np.float32(np.inf))
    return t


def _light_code(usable: np.ndarray) -> np.ndarray:
    """(h, w) code with bit k set where light k is usable (uint8 for K <= 8, else uint64)."""
    k = usable.shape[0]
    if k <= 8:
        code = usable[0].view(np.uint8).copy()
        for kk in range(1, k):
            code |= usable[kk].view(np.uint8) << np.uint8(kk)
        return code
    code = usable[0].astype(np.uint64)
    for kk in range(1, k):
        code |= usable[kk].astype(np.uint64) << np.uint64(kk)
    return code


def _solve_distant(
    values: np.ndarray,
    scaled: np.ndarray,
    usable: np.ndarray,
    code: np.ndarray,
    count: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """b = pinv(L_used) I per pixel for one (K, 3) light matrix; (3, h, w) and solved (h, w)."""
    k, h, w = values.shape
    flat = values.reshape(k, h * w)
    # The pixels with all K lights usable: one product with pinv(L) for all of them (einsum
    # runs single-threaded; OpenBLAS's threaded sgemm with a 3-row operand was several times
    # slower and erratic on the two busy cores). The other pixels' columns are overwritten
    # below, or left unsolved.
    solved = count == k
    if _degenerate(scaled[None])[0]:
        solved[:] = False
    pinv = np.linalg.pinv(scaled).astype(np.float32)
    b = np.einsum("ik,kn->in", pinv, flat)
    partial = np.flatnonzero((count >= 3) & (count < k))
    if partial.size:
        # One pseudo-inverse per pattern of usable lights, with zero columns for the unused
        # ones (the pseudo-inverse of L with those rows zeroed), solved in float64.
        patterns, group = np.unique(code.reshape(-1)[partial], return_inverse=True)
        bits = np.left_shift(np.uint64(1), np.arange(k, dtype=np.uint64))
        rows = (patterns.astype(np.uint64)[:, None] & bits) != 0  # (G, K)
        l_used = scaled[None, :, :] * rows[:, :, None]
        pinvs = np.linalg.pinv(l_used)  # (G, 3, K)
        good = ~_degenerate(l_used)[group]
        pix = partial[good]
        sub = flat[:, pix].astype(np.float64)
        sub[~usable.reshape(k, h * w)[:, pix]] = 0.0  # no NaN from unused values
        b[:, pix] = np.einsum("pik,kp->ip", pinvs[group[good]], sub)
        solved.reshape(-1)[pix] = True
    return b.reshape(3, h, w), solved


def _degenerate(scaled: np.ndarray) -> np.ndarray:
    """(G,) bool: light matrices (G, K, 3) whose smallest singular value is ~0 (relative)."""
    sv = np.linalg.svd(scaled, compute_uv=False)
    return sv[:, -1] <= _MIN_RELATIVE_SINGULAR_VALUE * sv[:, 0]


def _solve_per_pixel(
    values: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray,
    usable: np.ndarray,
    count: np.ndarray,
    box: tuple[slice, slice],
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form 3x3 normal equations per pixel (near lights); (3, h, w) and solved.

    A = sum_k a_k a_k^T and r = sum_k a_k I_k over the usable lights, a_k = e_k l_k; then
    b = A^-1 r = C r / det(A) with C the cofactor matrix of the symmetric A. ``count`` is
    lowered (in place) where a light's direction or intensity is unusable.
    """
    k, h, w = values.shape
    f32 = np.float32
    # a_k per component, light and pixel, times 0/1 for usable (products with a 0/1 plane:
    # several times cheaper than where=; NaN * 0 is repaired below).
    weights = np.empty((3, k, h, w), dtype=f32)
    masked = np.empty((k, h, w), dtype=f32)
    with np.errstate(invalid="ignore", over="ignore"):
        for kk in range(k):
            ok = usable[kk]
            if intensities.ndim == 3:
                e = intensities[kk][box]
                bad = ~((e > 0) & (e < np.inf))  # NaN compares False
                count -= ok & bad
                ok = ok & ~bad
            else:
                e = intensities[kk]
            scale = np.multiply(ok, e, dtype=f32)
            light = lights[kk][box] if lights.ndim == 4 else lights[kk]
            for c in range(3):
                np.multiply(light[..., c], scale, out=weights[c, kk], dtype=f32)
            np.multiply(values[kk], ok, out=masked[kk])
        # Sums over the lights, one einsum per entry (upper triangle of A, then r).
        sums = [
            np.einsum("khw,khw->hw", weights[i], other)
            for i, other in (
                (0, weights[0]), (0, weights[1]), (0, weights[2]),
                (1, weights[1]), (1, weights[2]), (2, weights[2]),
                (0, masked), (1, masked), (2, masked),
            )
        ]
        # Where a light's direction, intensity or value is not finite the sums are not
        # either (rare): sum those pixels again, leaving such lights out.
        check = sums[0] + sums[3] + sums[5] + sums[6] + sums[7] + sums[8]
        poisoned = np.flatnonzero(~(check < np.inf))
        if poisoned.size:
            _resum(poisoned, sums, values, lights, intensities, usable, count, box)
        a_xx, a_xy, a_xz, a_yy, a_yz, a_zz, r_x, r_y, r_z = sums
        # Cofactors of the symmetric A; A^-1 = C / det(A).
        c_xx = a_yy * a_zz - a_yz * a_yz
        c_xy = a_xz * a_yz - a_xy * a_zz
        c_xz = a_xy * a_yz - a_xz * a_yy
        c_yy = a_xx * a_zz - a_xz * a_xz
        c_yz = a_xy * a_xz - a_xx * a_yz
        c_zz = a_xx * a_yy - a_xy * a_xy
        det = a_xx * c_xx + a_xy * c_xy + a_xz * c_xz
        trace = a_xx + a_yy + a_zz
        trace *= f32(1.0 / 3.0)
        solved = (count >= 3) & (det > f32(_MIN_RELATIVE_DETERMINANT) * trace * trace * trace)
        inv_det = np.divide(f32(1.0), det, out=np.zeros_like(det), where=solved)
        b = np.empty((3, h, w), dtype=f32)
        for out, (cx, cy, cz) in zip(
            b, ((c_xx, c_xy, c_xz), (c_xy, c_yy, c_yz), (c_xz, c_yz, c_zz)), strict=True
        ):
            np.multiply(cx, r_x, out=out)
            out += cy * r_y
            out += cz * r_z
            out *= inv_det
    return b, solved


def _resum(
    pixels: np.ndarray,
    sums: list[np.ndarray],
    values: np.ndarray,
    lights: np.ndarray,
    intensities: np.ndarray,
    usable: np.ndarray,
    count: np.ndarray,
    box: tuple[slice, slice],
) -> None:
    """Recompute the normal-equation sums (and ``count``) at flat box ``pixels``, in place,
    leaving out every light whose direction, intensity or value is unusable there."""
    rows, cols = np.divmod(pixels, values.shape[2])
    at = (rows + box[0].start, cols + box[1].start)
    light = lights[:, at[0], at[1]] if lights.ndim == 4 else lights[:, None, :]
    e = intensities[:, at[0], at[1]] if intensities.ndim == 3 else intensities[:, None]
    value = values[:, rows, cols]
    with np.errstate(invalid="ignore"):
        ok = usable[:, rows, cols] & np.isfinite(light).all(axis=-1) & (e > 0) & (e < np.inf)
    a = np.where(ok[..., None], light * e[..., None], 0.0)  # (K, P, 3)
    value = np.where(ok, value, 0.0)
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    for acc, (i, j) in zip(sums[:6], pairs, strict=True):
        acc.reshape(-1)[pixels] = np.einsum("kp,kp->p", a[..., i], a[..., j])
    for acc, i in zip(sums[6:], range(3), strict=True):
        acc.reshape(-1)[pixels] = np.einsum("kp,kp->p", a[..., i], value)
    count.reshape(-1)[pixels] = ok.sum(axis=0)
