"""The calibration sphere's silhouette and centre (paper Sec. 3.1, Eq. 8-9): sub-pixel
points of its outline (`sphere_edge_points`) and the centre S fitted to the rays tangent to
it (`fit_sphere_center`), with the pixel geometry both use (camera matrix, rays through
pixels, undistortion, the outline's circle in the image).

Geometry in the camera optical frame (x right, y down, z forward, metres), camera centre at
the origin; the ray through pixel (u, v) is K^-1 (u, v, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage, optimize

from fingerps_calib.errors import FingerpsCalibError

#: Radii (metres) a calibration sphere can have in front of a fingerprint camera: below
#: 0.5 mm its silhouette is a few pixels wide at the working distance (~90 mm) and cannot be
#: fitted; above 50 mm it cannot be seen whole. Ball bearings of 2-25 mm are the usual ones.
RADIUS_RANGE_M = (0.5e-3, 50e-3)


def check_radius(radius_m: float) -> None:
    """Raise `FingerpsCalibError` unless ``radius_m`` is a number within `RADIUS_RANGE_M`.

    Radii outside it fail inside the fit rather than being refused (1e-300 divides by zero,
    1e300 overflows, inf or NaN poisons the solver).
    """
    lo, hi = RADIUS_RANGE_M
    try:
        radius = float(radius_m)
    except (TypeError, ValueError):
        radius = float("nan")
    if not lo <= radius <= hi:  # False for NaN too
        raise FingerpsCalibError(
            f"radius_m = {radius_m!r} must be a finite sphere radius in metres between "
            f"{lo:g} and {hi:g} ({1e3 * lo:g}-{1e3 * hi:g} mm); measure the sphere and give "
            "its radius in metres (4 mm is 0.004)")


@dataclass(frozen=True, eq=False)
class SphereFit:
    """The sphere fitted to its silhouette (paper Eq. 9).

    Attributes
    ----------
    center_optical_m : (3,) float64
        Sphere centre S in the optical frame, metres.
    radius_m : float
        The known radius r the fit used, metres.
    residuals_px : (N,) float64
        Signed distance of each edge point to the fitted sphere's silhouette, pixels:
        the Sampson (first-order geometric) distance to the silhouette conic
        x^T K^-T (S S^T - (|S|^2 - r^2) I) K^-1 x = 0; positive inside the silhouette.
    rms_residual_px : float
        Root mean square of ``residuals_px``.
    silhouette_center_uv : (2,) float64
        Centre of the circle fitted to the edge points (the initial guess), pixels.
    silhouette_radius_px : float
        Radius of that circle, pixels.
    converged : bool
        The least-squares solver reported convergence.
    """

    center_optical_m: np.ndarray
    radius_m: float
    residuals_px: np.ndarray
    rms_residual_px: float
    silhouette_center_uv: np.ndarray
    silhouette_radius_px: float
    converged: bool


def sphere_edge_points(
    images: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    smoothing_sigma_px: float = 0.5,
    search_half_width_px: float = 5.0,
) -> np.ndarray:
    """Sub-pixel points of the sphere's silhouette.

    Without a mask, the sphere (its weak diffuse component against a dark background) is
    segmented in the pixel-wise maximum over the images: threshold by Otsu's method on the
    pixel-wise median (free of the highlights; the maximum if there are fewer than three
    images) clipped at its 99.5th percentile, largest connected component, holes filled.
    An ellipse fitted to that outline (less any part along the image border) gives one
    search line per pixel of perimeter, through the ellipse's centre; along each line the
    pixel-wise maximum (smoothed by a Gaussian of ``smoothing_sigma_px``) is sampled every
    0.25 px with cubic interpolation and the edge is put at the peak of the outward
    intensity drop, refined by a parabola through the three samples around it. With
    ``mask`` the same refinement runs on the mask's boundary (the 0/1 mask, smoothed), so
    the points lie half-way between inside and outside pixels.

    Search lines that leave the image, or whose edge is weak (below a quarter of the
    median edge strength), give no point; so a sphere cut by the image border still gives
    the points of its visible outline.

    Bias: the diffuse shading of a sphere lit from near the camera falls steeply towards the
    limb (as the root of the distance to it), which pulls the gradient peak inwards. On the
    simulated rig (fingerps_driver.simulation) the points lie 0.10 px inside the true
    silhouette on average with the default smoothing (0.19 px with sigma = 1 px), which
    puts the fitted centre ~0.08 % too far; with a mask there is no such bias.

    Parameters
    ----------
    images : (K, H, W) or (H, W) array, any real dtype
        Images of the sphere (one per LED).
    mask : (H, W) bool array, optional
        The sphere's pixels; if given, its boundary is used instead of segmenting.
    smoothing_sigma_px : float
        Gaussian smoothing before the gradient, pixels; raise it for noisy images.
    search_half_width_px : float
        Half length of each search line around the ellipse, pixels.

    Returns
    -------
    (N, 2) float64
        Edge points (u, v), pixels; empty (0, 2) if no sphere was found.

    Raises
    ------
    FingerpsCalibError
        Bad shapes.
    """
    stack = as_image_stack(images, "images")
    h, w = stack.shape[1:]
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise FingerpsCalibError(
                f"mask has shape {mask.shape}, the images are {h}x{w}; pass a mask of the "
                "images' size"
            )
        region = _largest_component(mask.astype(bool))
        field = mask.astype(bool).astype(np.float64)
    else:
        field = stack.max(axis=0)
        # The threshold comes from the median over the LEDs (each highlight shows in one
        # image only, so it is gone there) when there are enough images.
        level = _otsu_level(np.median(stack, axis=0) if len(stack) >= 3 else field)
        region = None if level is None else _largest_component(
            cv2.morphologyEx((field > level).astype(np.uint8), cv2.MORPH_OPEN,
                             np.ones((3, 3), np.uint8)).astype(bool)
        )
    if region is None:
        return np.zeros((0, 2))
    contours, _ = cv2.findContours(
        region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    outline = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    # Where the sphere is cut by the image border the outline runs along the border.
    on_border = (
        (outline[:, 0] <= 0) | (outline[:, 0] >= w - 1)
        | (outline[:, 1] <= 0) | (outline[:, 1] >= h - 1)
    )
    outline = outline[~on_border]
    if len(outline) < 5:
        return np.zeros((0, 2))
    (ecx, ecy), (ea, eb), angle_deg = cv2.fitEllipse(outline.astype(np.float32))
    n_lines = max(32, int(np.pi * (ea + eb) / 2))  # about one per pixel of perimeter
    phi = np.linspace(0.0, 2 * np.pi, n_lines, endpoint=False)
    direction = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    radius = _ellipse_radius(phi, ea / 2, eb / 2, np.deg2rad(angle_deg))

    smooth = ndimage.gaussian_filter(field, smoothing_sigma_px, mode="nearest")
    step = 0.25
    s = np.arange(-search_half_width_px, search_half_width_px + step / 2, step)
    dist = radius[:, None] + s[None, :]  # (L, S) distance from the centre along each line
    u = ecx + direction[:, :1] * dist
    v = ecy + direction[:, 1:] * dist
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    profile = ndimage.map_coordinates(smooth, [v.ravel(), u.ravel()], order=3,
                                      mode="nearest").reshape(u.shape)
    drop = -np.gradient(profile, step, axis=1)  # outward intensity drop, per pixel
    peak = np.argmax(drop, axis=1)
    rows = np.arange(n_lines)
    valid = inside.all(axis=1) & (peak > 0) & (peak < len(s) - 1)
    strength = drop[rows, peak]
    if not np.any(valid):
        return np.zeros((0, 2))
    valid &= strength > 0.25 * np.median(strength[valid])
    p = np.clip(peak, 1, len(s) - 2)
    y0, y1, y2 = drop[rows, p - 1], drop[rows, p], drop[rows, p + 1]
    denom = y0 - 2 * y1 + y2
    offset = np.where(denom < 0, 0.5 * (y0 - y2) / np.where(denom < 0, denom, -1.0), 0.0)
    edge = radius + s[p] + np.clip(offset, -0.5, 0.5) * step
    points = np.stack([ecx + direction[:, 0] * edge, ecy + direction[:, 1] * edge], axis=1)
    return points[valid]


def fit_sphere_center(
    edge_uv: np.ndarray, *, camera_matrix: np.ndarray, radius_m: float
) -> SphereFit:
    """Fit the sphere centre S to its silhouette points (paper Eq. 8, 9).

    The rays through the edge points are tangent to the sphere: the distance from S to each
    ray equals r. Minimises sum_i rho(dist_i(S) - r) with `scipy.optimize.least_squares`
    (soft-L1 loss, scale about half a pixel), the geometric form of Eq. 9: the paper's
    h_i - r^2 = dist_i^2 - r^2 ~ 2 r (dist_i - r) has the same minimiser for exact data.
    Initial guess: a circle fitted to the edge points gives the centre direction and the
    apparent angular radius alpha, hence |S| = r / sin(alpha).

    Parameters
    ----------
    edge_uv : (N, 2) float
        Silhouette points (u, v), ideal pixel coordinates, N >= 5.
    camera_matrix : (3, 3) float
        K.
    radius_m : float
        Sphere radius r, metres.

    Returns
    -------
    SphereFit
        ``residuals_px`` are Sampson distances to the fitted silhouette (see `SphereFit`).

    Raises
    ------
    FingerpsCalibError
        Bad shapes, too few points, or a radius outside `RADIUS_RANGE_M`.
    """
    edge_uv = np.asarray(edge_uv, dtype=np.float64)
    k = checked_camera_matrix(camera_matrix)
    if edge_uv.ndim != 2 or edge_uv.shape[1] != 2 or len(edge_uv) < 5:
        raise FingerpsCalibError(
            f"edge_uv has shape {edge_uv.shape}, expected (N, 2) with N >= 5; is the sphere "
            "visible in the images?"
        )
    check_radius(radius_m)
    rays = pixel_rays(edge_uv, k)
    (uc, vc), rho = fit_circle(edge_uv)
    f = float(np.sqrt(k[0, 0] * k[1, 1]))
    alpha = np.arctan(rho / f)
    s0 = pixel_rays(np.array([[uc, vc]]), k)[0] * radius_m / np.sin(alpha)
    tangent_distance = np.sqrt(max(s0 @ s0 - radius_m**2, 1e-12))

    def residual(s: np.ndarray) -> np.ndarray:
        along = rays @ s
        return np.sqrt(np.maximum(s @ s - along**2, 0.0)) - radius_m

    solution = optimize.least_squares(
        residual, s0, loss="soft_l1", f_scale=0.5 * tangent_distance / f,
        x_scale=np.full(3, radius_m), method="trf",
    )
    center = solution.x
    residuals_px = _silhouette_sampson(edge_uv, k, center, radius_m)
    return SphereFit(
        center_optical_m=center,
        radius_m=float(radius_m),
        residuals_px=residuals_px,
        rms_residual_px=float(np.sqrt(np.mean(residuals_px**2))),
        silhouette_center_uv=np.array([uc, vc]),
        silhouette_radius_px=float(rho),
        converged=bool(solution.success),
    )


def as_image_stack(images: np.ndarray, name: str) -> np.ndarray:
    stack = np.asarray(images)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3 or stack.shape[0] < 1 or not np.issubdtype(stack.dtype, np.number):
        raise FingerpsCalibError(
            f"{name} has shape {stack.shape} ({stack.dtype}), expected (K, H, W) or (H, W) "
            "numbers"
        )
    return stack.astype(np.float64)


def silhouette_contrast(stack: np.ndarray, center: np.ndarray, radius: float) -> float:
    """Step across a circular outline in the pixel-wise maximum, in units of the noise.

    Median of a ring 2-6 px inside minus that of a ring 2-6 px outside, divided by the
    outside ring's robust standard deviation (at least one digital unit for integer
    images). ~12 for the simulated rig's sphere, ~3 with four times its read noise, 0 for
    an empty view.
    """
    field = stack.max(axis=0).astype(np.float64)
    h, w = field.shape
    vv, uu = np.mgrid[0:h, 0:w]
    distance = np.hypot(uu - center[0], vv - center[1])
    inner = field[(distance > radius - 6) & (distance < radius - 2)]
    outer = field[(distance > radius + 2) & (distance < radius + 6)]
    if inner.size == 0 or outer.size == 0:
        return 0.0
    background = float(np.median(outer))
    sigma = 1.4826 * float(np.median(np.abs(outer - background)))
    floor = 1.0 if np.issubdtype(stack.dtype, np.integer) else 1e-12
    return (float(np.median(inner)) - background) / max(sigma, floor)


def checked_camera_matrix(camera_matrix: np.ndarray) -> np.ndarray:
    k = np.asarray(camera_matrix, dtype=np.float64)
    if k.shape != (3, 3) or not (k[0, 0] > 0 and k[1, 1] > 0) or not np.all(np.isfinite(k)):
        raise FingerpsCalibError(
            f"camera_matrix has shape {k.shape}, expected (3, 3) [[fx,0,cx],[0,fy,cy],[0,0,1]] "
            "finite, with fx, fy > 0; load it with "
            "fingerps_calib.intrinsics.camera_info_yaml.load_camera_info"
        )
    return k


def pixel_rays(uv: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(N, 3) unit rays K^-1 (u, v, 1) of (N, 2) pixels, optical frame."""
    homogeneous = np.column_stack([uv, np.ones(len(uv))])
    rays = np.linalg.solve(k, homogeneous.T).T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit: centre (2,) and radius of (N, 2) points."""
    x, y = points[:, 0], points[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    (bx, by, c), *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    center = np.array([bx / 2, by / 2])
    return center, float(np.sqrt(c + center @ center))


def undistort_points(uv: np.ndarray, k: np.ndarray, distortion: np.ndarray | None) -> np.ndarray:
    if distortion is None:
        return uv
    points = uv.reshape(-1, 1, 2).astype(np.float64)
    coeffs = np.asarray(distortion, dtype=np.float64).ravel()
    return cv2.undistortPoints(points, k, coeffs, P=k).reshape(-1, 2)


def _silhouette_sampson(uv: np.ndarray, k: np.ndarray, s: np.ndarray, r: float) -> np.ndarray:
    """Signed Sampson distance (pixels) of points to the sphere's silhouette conic."""
    k_inv = np.linalg.inv(k)
    cone = np.outer(s, s) - (s @ s - r * r) * np.eye(3)
    conic = k_inv.T @ cone @ k_inv
    x = np.column_stack([uv, np.ones(len(uv))])
    qx = x @ conic
    value = np.einsum("ij,ij->i", qx, x)
    return value / (2.0 * np.linalg.norm(qx[:, :2], axis=1))


def _ellipse_radius(phi: np.ndarray, a: float, b: float, theta: float) -> np.ndarray:
    """Distance from an ellipse's centre to its boundary along direction ``phi``."""
    c, s = np.cos(phi - theta), np.sin(phi - theta)
    return 1.0 / np.sqrt((c / a) ** 2 + (s / b) ** 2)


def _largest_component(binary: np.ndarray) -> np.ndarray | None:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary.astype(np.uint8), 8)
    if n < 2:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return ndimage.binary_fill_holes(labels == best)


def _otsu_level(field: np.ndarray) -> float | None:
    """Otsu threshold of ``field`` (clipped at its 99.5th percentile), in its own units."""
    low, high = np.percentile(field, [1.0, 99.5])
    if not high > low:
        return None
    scaled = np.clip((field - low) / (high - low), 0.0, 1.0)
    gray = cv2.GaussianBlur((scaled * 255).astype(np.uint8), (5, 5), 0)
    level, _ = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(low + (level + 0.5) / 255.0 * (high - low))
