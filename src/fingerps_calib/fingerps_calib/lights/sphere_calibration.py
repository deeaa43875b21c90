"""Light directions from images of a shiny sphere of known radius (paper Sec. 3.1, Eq. 8-10).

Geometry in the camera optical frame (x right, y down, z forward, metres), camera centre
at the origin; the ray through pixel (u, v) is K^-1 (u, v, 1), i.e. (u - cx, v - cy, f)
when fx = fy = f. Pixel coordinates (u, v) are ideal (undistorted) ones unless a function
takes ``distortion``. See ../shared/paper/NOTES.md Sec. 3.1.

Steps (`calibrate_lights`):

1. `sphere_edge_points`: sub-pixel silhouette points of the sphere.
2. `fit_sphere_center`: the sphere centre S from the tangent rays (Eq. 8, 9).
3. `highlight_centroid`: the specular highlight of each LED.
4. `light_direction`: the mirror reflection at the highlight (Eq. 10).

`calibrate_lights_orthographic` is the classic chrome-sphere method for public data sets
without intrinsics (orthographic camera, directions in the PS frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage, optimize

from fingerps_calib.errors import FingerpsCalibError
from fingerps_recon.photometric.frames import optical_to_ps

#: Gaussian smoothing (pixels) of the silhouette search, tried in turn while the sphere fit's
#: rms exceeds the limit: noisy images need more. A real misfit (a wrong camera matrix, an
#: occluded or out-of-round silhouette) stays above the limit at every smoothing.
_EDGE_SMOOTHING_PX = (0.5, 1.0, 1.5, 2.0)

#: Relative thresholds at which the highlight centroid is recomputed to measure its
#: stability (`LightCalibrationResult.residuals_px`); the middle one gives the centroid.
_STABILITY_THRESHOLDS = (0.3, 0.5, 0.7)

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


@dataclass(frozen=True, eq=False)
class LightCalibrationResult:
    """Light directions from a shiny sphere (`calibrate_lights`).

    Attributes
    ----------
    directions_optical : (K, 3) float64
        Unit vector from the sphere's highlight point towards LED k, optical frame;
        NaN for an LED whose highlight was not found.
    highlights_uv : (K, 2) float64
        Highlight centroids, ideal pixel coordinates; NaN where not found.
    residuals_px : (K,) float64
        Stability of each highlight centroid: the largest distance between the centroid at
        relative threshold 0.5 and the centroids at 0.3 and 0.7 of the blob's range above
        the disc's median (pixels). A clean, symmetric highlight gives a few hundredths of a
        pixel; a highlight merged with a second reflection or cut by the limb gives more.
        (The distance to the "reprojected" highlight would be zero by construction.)
    sphere_center_optical_m : (3,) float64
        Fitted sphere centre, metres; NaN if the sphere was not found.
    edge_rms_px : float
        RMS distance of the edge points to the fitted silhouette (`SphereFit`), pixels.
    ok : bool
        Every check passed; if False, ``problems`` says why and what to do.
    problems : tuple of str
    highlight_points_optical_m : (K, 3) float64
        The surface points S1 where the rays through the highlights meet the sphere,
        metres; NaN where not found. With ``directions_optical`` they are the rays towards
        the LEDs that `fingerps_calib.lights.led_triangulation` intersects.
    radius_m : float
        The sphere radius used.
    edge_points_uv : (N, 2) float64
        The silhouette points found, raw (distorted) pixel coordinates.
    highlight_contrast : (K,) float64
        Peak of each highlight above the disc's median, divided by that of the brightest
        part of the disc away from the highlight (99.9th percentile beyond twice the blob's
        radius + 5 px); NaN where not found. ~30 on the simulated rig.
    saturated_px : (K,) int64
        Pixels of each highlight at or above the saturation level (0 if unknown).
    """

    directions_optical: np.ndarray
    highlights_uv: np.ndarray
    residuals_px: np.ndarray
    sphere_center_optical_m: np.ndarray
    edge_rms_px: float
    ok: bool
    problems: tuple[str, ...]
    highlight_points_optical_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    radius_m: float = float("nan")
    edge_points_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    highlight_contrast: np.ndarray = field(default_factory=lambda: np.zeros(0))
    saturated_px: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def directions_ps(self) -> np.ndarray:
        """(K, 3) float64: ``directions_optical`` in the PS frame (diag(1, -1, -1))."""
        return optical_to_ps(self.directions_optical)


@dataclass(frozen=True, eq=False)
class OrthographicLightResult:
    """Light directions from a chrome sphere under an orthographic camera.

    Attributes
    ----------
    directions_ps : (K, 3) float64
        Unit light directions in the PS frame (view direction (0, 0, 1)); NaN where the
        highlight was not found.
    highlights_uv : (K, 2) float64
    circle_center_uv : (2,) float64
    circle_radius_px : float
    ok : bool
    problems : tuple of str
    edge_rms_px : float
        RMS distance of the silhouette points from the fitted circle, pixels.
    edge_points_uv : (N, 2) float64
        The silhouette points.
    residuals_px : (K,) float64
        Stability of each highlight centroid, as `LightCalibrationResult.residuals_px`.
    """

    directions_ps: np.ndarray
    highlights_uv: np.ndarray
    circle_center_uv: np.ndarray
    circle_radius_px: float
    ok: bool
    problems: tuple[str, ...]
    edge_rms_px: float = float("nan")
    edge_points_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


# --------------------------------------------------------------------------- edge points


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
    stack = _as_stack(images, "images")
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


# ---------------------------------------------------------------------------- sphere fit


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
    k = _camera_matrix(camera_matrix)
    if edge_uv.ndim != 2 or edge_uv.shape[1] != 2 or len(edge_uv) < 5:
        raise FingerpsCalibError(
            f"edge_uv has shape {edge_uv.shape}, expected (N, 2) with N >= 5; is the sphere "
            "visible in the images?"
        )
    check_radius(radius_m)
    rays = _rays(edge_uv, k)
    (uc, vc), rho = _fit_circle(edge_uv)
    f = float(np.sqrt(k[0, 0] * k[1, 1]))
    alpha = np.arctan(rho / f)
    s0 = _rays(np.array([[uc, vc]]), k)[0] * radius_m / np.sin(alpha)
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


# ----------------------------------------------------------------------------- highlight


def highlight_centroid(
    image: np.ndarray,
    *,
    disc_center_uv: np.ndarray,
    disc_radius_px: float,
    relative_threshold: float = 0.5,
) -> tuple[float, float]:
    """Centroid of the specular highlight of one LED inside the sphere's disc.

    Pixels inside the disc brighter than ``background + relative_threshold * (peak -
    background)`` (background: the disc's median, peak: its maximum) form blobs; the blob
    with the largest summed excess wins (a weaker second reflection is dropped), and its
    centroid weighted by the excess is returned. A saturated highlight is a flat plateau
    whose weighted centroid is its centre, so saturation does no harm.

    Parameters
    ----------
    image : (H, W) array, any real dtype
    disc_center_uv : (2,) float
        Centre of the sphere's image, pixels.
    disc_radius_px : float
        Radius of the search disc, pixels (the sphere's, less a small margin).
    relative_threshold : float
        In (0, 1).

    Returns
    -------
    (u, v) : tuple of float
        Pixel coordinates of the highlight.

    Raises
    ------
    FingerpsCalibError
        Bad shapes, or no highlight in the disc.
    """
    found = _highlight(image, disc_center_uv, disc_radius_px, (relative_threshold,))
    return found.u, found.v


@dataclass(frozen=True)
class _Highlight:
    """One highlight: centroid (u, v), its stability and the numbers the checks use."""

    u: float
    v: float
    spread_px: float
    contrast: float        # peak - background (the disc's median)
    shading: float         # brightest part of the disc away from the blob - background
    saturated_px: int      # pixels of the chosen blob at or above the saturation level
    background: float


def _highlight(
    image: np.ndarray,
    disc_center_uv: np.ndarray,
    disc_radius_px: float,
    thresholds: tuple[float, ...],
    *,
    saturation_level: float | None = None,
) -> _Highlight:
    """Highlight centroid at the middle threshold and its stability (see module doc)."""
    image = np.asarray(image)
    if image.ndim != 2 or not np.issubdtype(image.dtype, np.number):
        raise FingerpsCalibError(f"image has shape {image.shape}, expected (H, W) numbers")
    for t in thresholds:
        if not 0.0 < t < 1.0:
            raise FingerpsCalibError(f"relative_threshold {t} must lie in (0, 1)")
    cu, cv = (float(x) for x in np.asarray(disc_center_uv, dtype=np.float64).ravel()[:2])
    h, w = image.shape
    vv, uu = np.mgrid[0:h, 0:w]
    disc = (uu - cu) ** 2 + (vv - cv) ** 2 <= disc_radius_px**2
    if not np.any(disc):
        raise FingerpsCalibError(
            f"the disc at ({cu:.1f}, {cv:.1f}) radius {disc_radius_px:.1f} px holds no "
            "pixel of the image; check the sphere fit"
        )
    values = image.astype(np.float64)
    inside = values[disc]
    background = float(np.median(inside))
    peak = float(inside.max())
    if saturation_level is not None and background >= 0.95 * saturation_level:
        raise FingerpsCalibError(
            "the whole sphere is saturated; lower the exposure or the LED level")
    if not peak > background:
        raise FingerpsCalibError(
            "no highlight inside the sphere's disc (it is uniform); check that the LED lit "
            "and that its reflection is visible on the sphere"
        )
    main = thresholds[len(thresholds) // 2]
    cut = background + main * (peak - background)
    excess = np.where(disc, values - cut, 0.0)
    n, labels = cv2.connectedComponents((excess > 0).astype(np.uint8), connectivity=8)
    weight = ndimage.sum_labels(excess, labels, index=np.arange(1, n))
    best = 1 + int(np.argmax(weight))
    blob = labels == best
    centroid = _weighted_centroid(np.where(blob, excess, 0.0))
    # What the highlight must stand out from: the brightest part of the disc away from it
    # (diffuse shading, noise, other reflections), beyond twice the blob's radius + 5 px
    # (at most a quarter of the disc's radius: a "blob" of diffuse shading is no highlight).
    reach = min(2.0 * np.sqrt(blob.sum() / np.pi) + 5.0, 0.25 * disc_radius_px)
    away = disc & ((uu - centroid[0]) ** 2 + (vv - centroid[1]) ** 2 > reach**2)
    floor = 1.0 if np.issubdtype(image.dtype, np.integer) else 1e-12
    elsewhere = float(np.percentile(values[away], 99.9)) if np.any(away) else background
    shading = max(elsewhere - background, floor)
    saturated = 0
    if saturation_level is not None:
        # The saturated plateau holding the blob (it may reach beyond the blob's cut).
        hot, _ = ndimage.label(disc & (values >= saturation_level), structure=np.ones((3, 3)))
        touched = np.unique(hot[blob & (hot > 0)])
        saturated = int(np.isin(hot, touched).sum()) if touched.size else 0
    # Stability: the centroid at other thresholds, within the component holding this blob.
    spread = 0.0
    seed = np.unravel_index(np.argmax(np.where(blob, values, -np.inf)), values.shape)
    for t in thresholds:
        if t == main:
            continue
        ex = np.where(disc, values - (background + t * (peak - background)), 0.0)
        lab, _ = ndimage.label(ex > 0, structure=np.ones((3, 3)))
        if lab[seed] == 0:
            continue
        other = _weighted_centroid(np.where(lab == lab[seed], ex, 0.0))
        spread = max(spread, float(np.hypot(*(other - centroid))))
    return _Highlight(float(centroid[0]), float(centroid[1]), spread, peak - background,
                      shading, saturated, background)


# ---------------------------------------------------------------------- light direction


def light_direction(
    highlight_uv: np.ndarray,
    *,
    sphere_center: np.ndarray,
    radius_m: float,
    camera_matrix: np.ndarray,
) -> np.ndarray:
    """Direction towards the LED whose highlight is at ``highlight_uv`` (paper Eq. 10).

    The ray d through the highlight meets the sphere (nearest root) at S1; N = (S1 - S)/r,
    R = -d (unit, from S1 towards the camera centre), l = 2 (N.R) N - R.

    Parameters
    ----------
    highlight_uv : (2,) float
        Ideal pixel coordinates.
    sphere_center : (3,) float
        S, optical frame, metres.
    radius_m : float
    camera_matrix : (3, 3) float

    Returns
    -------
    (3,) float64
        Unit vector from S1 towards the LED, optical frame.

    Raises
    ------
    FingerpsCalibError
        The ray misses the sphere, or bad shapes.
    """
    k = _camera_matrix(camera_matrix)
    uv = np.asarray(highlight_uv, dtype=np.float64)
    s = np.asarray(sphere_center, dtype=np.float64)
    if uv.shape != (2,) or s.shape != (3,):
        raise FingerpsCalibError(
            f"highlight_uv {uv.shape} / sphere_center {s.shape}: expected (2,) and (3,)"
        )
    return _mirror_ray(uv, s, radius_m, k)[0]


def _mirror_ray(
    uv: np.ndarray, s: np.ndarray, radius_m: float, k: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction towards the light and the surface point S1 (Eq. 10)."""
    d = _rays(uv[None, :], k)[0]
    along = d @ s
    disc = along**2 - s @ s + radius_m**2
    if disc < 0 or along <= 0:
        raise FingerpsCalibError(
            f"the ray through the highlight ({uv[0]:.1f}, {uv[1]:.1f}) misses the sphere; "
            "the highlight lies outside the sphere's image or the sphere fit is wrong"
        )
    s1 = (along - np.sqrt(disc)) * d
    normal = (s1 - s) / radius_m
    r = -d
    light = 2.0 * (normal @ r) * normal - r
    return light / np.linalg.norm(light), s1


# --------------------------------------------------------------------------- calibration


def calibrate_lights(
    images: np.ndarray,
    *,
    camera_matrix: np.ndarray,
    radius_m: float,
    mask: np.ndarray | None = None,
    distortion: np.ndarray | None = None,
    edge_rms_limit_px: float = 0.5,
    residual_limit_px: float = 1.0,
    saturation_level: float | None = None,
    min_highlight_contrast: float = 2.0,
    max_saturated_fraction: float = 0.01,
    require_whole_sphere: bool = False,
    expected_distance_m: tuple[float, float] | None = None,
) -> LightCalibrationResult:
    """Light directions of K LEDs from K images of a shiny sphere (paper Sec. 3.1).

    The silhouette points (`sphere_edge_points`) are searched with a Gaussian smoothing of
    0.5 px, raised to 1, 1.5 and 2 px while the sphere fit's rms exceeds
    ``edge_rms_limit_px``: noise breaks up a faint edge, and a wider smoothing only pulls
    the points a little inwards (on the simulated rig with four times the read noise and a
    quarter of the full well: 1.7 px rms at 0.5 px, 0.35 px rms and a 0.3 mm centre error
    at 1.5 px).

    Checks, each failing one adds a reason to ``problems`` and makes ``ok`` False:

    - the sphere is found (a silhouette standing out from the noise), its fit converged in
      front of the camera and fits to within five times ``edge_rms_limit_px`` (else nothing
      more is checked: the object is not the sphere); the silhouette fits within
      ``edge_rms_limit_px`` and is seen along most of its outline; with
      ``require_whole_sphere`` the silhouette lies wholly inside the image;
    - with ``expected_distance_m``, the fitted centre's distance from the camera lies in
      that range. The silhouette is a cone, the same for a sphere of radius r at distance d
      as for one of radius 2r at 2d, so neither the edge residual nor the directions can
      reveal a wrong radius: only the distance it implies can;
    - for each LED: the sphere's disc is not saturated; the highlight's peak above the
      disc's median is at least ``min_highlight_contrast`` times that of the brightest part
      of the disc away from it (diffuse shading, noise), and at least a fifth of the median
      highlight's (otherwise the LED did not light, or its
      reflection misses the sphere); with a known saturation level its saturated blob covers
      at most ``max_saturated_fraction`` of the disc; it is not at the limb; its stability
      (``residuals_px``) is within ``residual_limit_px``; and its direction points to the
      camera side (z_optical < 0).

    Parameters
    ----------
    images : (K, H, W) array, any real dtype
        Image k taken under LED k alone.
    camera_matrix : (3, 3) float
        K of the camera.
    radius_m : float
        Radius of the sphere, metres, within `RADIUS_RANGE_M`.
    mask : (H, W) bool, optional
        The sphere's pixels (then its boundary gives the silhouette).
    distortion : (n,) float, optional
        OpenCV distortion coefficients; if given, edge points and highlights are undistorted
        before the geometry. Without it the images must be undistorted already.
    edge_rms_limit_px, residual_limit_px : float
        Limits of the checks above, pixels.
    saturation_level : float, optional
        Full-scale value of the images; default the dtype's maximum for integer images,
        none (no saturation checks) for floating-point images.
    min_highlight_contrast : float
        See the checks.
    max_saturated_fraction : float
        See the checks. A saturated plateau's centroid is its centre, so a symmetric one does
        no harm (on the simulated rig a 4 px blur with 460 saturated pixels still gives
        0.06 deg); but the plateau hides the peak, and it is the same at every threshold, so
        the stability check cannot see a bloom or a second reflection merged into it.
    require_whole_sphere : bool
        Refuse a sphere cut by the image border (a partial outline still gives a fit, but
        a less certain one).
    expected_distance_m : (float, float), optional
        Range of the distance from the camera centre to the sphere centre, metres.

    Returns
    -------
    LightCalibrationResult

    Raises
    ------
    FingerpsCalibError
        Bad input shapes, or a radius outside `RADIUS_RANGE_M`.
    """
    stack = np.asarray(images)
    if stack.ndim != 3 or stack.shape[0] < 1 or not np.issubdtype(stack.dtype, np.number):
        raise FingerpsCalibError(
            f"images has shape {stack.shape} ({stack.dtype}), expected (K, H, W) numbers, "
            "one image per LED"
        )
    if np.issubdtype(stack.dtype, np.floating) and not np.all(np.isfinite(stack)):
        raise FingerpsCalibError(
            "the sphere images hold NaN or infinite pixels; capture them again")
    k = _camera_matrix(camera_matrix)
    check_radius(radius_m)
    if saturation_level is None and np.issubdtype(stack.dtype, np.integer):
        saturation_level = float(np.iinfo(stack.dtype).max)
    n_led, h, w = stack.shape
    directions = np.full((n_led, 3), np.nan)
    points = np.full((n_led, 3), np.nan)
    highlights = np.full((n_led, 2), np.nan)
    residuals = np.full(n_led, np.nan)
    contrast = np.full(n_led, np.nan)
    saturated = np.zeros(n_led, np.int64)
    problems: list[str] = []
    raw_edges = np.zeros((0, 2))

    def result(center: np.ndarray, edge_rms: float) -> LightCalibrationResult:
        return LightCalibrationResult(
            directions, highlights, residuals, center, edge_rms, not problems,
            tuple(problems), highlight_points_optical_m=points, radius_m=float(radius_m),
            edge_points_uv=raw_edges, highlight_contrast=contrast, saturated_px=saturated,
        )

    for smoothing in _EDGE_SMOOTHING_PX:
        raw_edges = sphere_edge_points(stack, mask=mask, smoothing_sigma_px=smoothing)
        if len(raw_edges) < 20:
            problems.append(
                "sphere not found: fewer than 20 points of its silhouette; put the whole "
                "sphere in view against a dark background (or pass a mask)"
            )
            return result(np.full(3, np.nan), float("nan"))
        edges = _undistort(raw_edges, k, distortion)
        fit = fit_sphere_center(edges, camera_matrix=k, radius_m=radius_m)
        if fit.rms_residual_px <= edge_rms_limit_px:
            break
    center = fit.center_optical_m
    disc_center_raw, disc_radius = _fit_circle(raw_edges)
    step = _silhouette_contrast(stack, disc_center_raw, disc_radius)
    if mask is None and not step >= 2.0:
        problems.append(
            f"sphere not found: no clear silhouette (the outline found stands out only "
            f"{step:.1f}x the noise); put the whole sphere in view against a dark background "
            "(or pass a mask)"
        )
        return result(np.full(3, np.nan), float("nan"))
    if not fit.converged or not center[2] > radius_m:
        problems.append(
            f"sphere fit failed (converged={fit.converged}, centre {center.round(4).tolist()}"
            " m); check the radius and the camera matrix"
        )
        return result(center, fit.rms_residual_px)
    if fit.rms_residual_px > 5.0 * edge_rms_limit_px:
        problems.append(
            f"the object in view is not the sphere: its silhouette fits a sphere to "
            f"{fit.rms_residual_px:.1f} px rms (at most {edge_rms_limit_px} px); put the "
            "sphere in view, alone, against a dark background (if it is the sphere, check "
            "the camera matrix)"
        )
        return result(center, fit.rms_residual_px)
    if require_whole_sphere:
        sides = [name for name, outside in (
            ("left", disc_center_raw[0] - disc_radius < 1.0),
            ("right", disc_center_raw[0] + disc_radius > w - 2.0),
            ("top", disc_center_raw[1] - disc_radius < 1.0),
            ("bottom", disc_center_raw[1] + disc_radius > h - 2.0),
        ) if outside]
        if sides:
            problems.append(
                f"the sphere is cut by the image border ({', '.join(sides)}): move it towards "
                "the middle of the view so that all of it is seen"
            )
    expected = np.pi * 2 * fit.silhouette_radius_px
    if len(raw_edges) < 0.5 * expected:
        problems.append(
            f"sphere edge found on only {len(raw_edges)} of ~{expected:.0f} outline points; "
            "is the sphere cut by the image border or occluded by its holder?"
        )
    if fit.rms_residual_px > edge_rms_limit_px:
        problems.append(
            f"sphere silhouette fits to {fit.rms_residual_px:.2f} px rms > "
            f"{edge_rms_limit_px} px; check the camera matrix, the focus and that nothing "
            "else bright touches the sphere"
        )
    if expected_distance_m is not None:
        near, far = expected_distance_m
        distance = float(np.linalg.norm(center))
        if not near <= distance <= far:
            middle = 0.5 * (near + far)
            problems.append(
                f"the sphere centre fits at {1e3 * distance:.1f} mm from the camera, outside "
                f"the expected {1e3 * near:.0f}-{1e3 * far:.0f} mm: is the radius right? "
                f"{1e3 * radius_m:.2f} mm was given; at {1e3 * middle:.0f} mm this sphere "
                f"would have a radius of {1e3 * radius_m * middle / distance:.2f} mm"
            )

    # The disc is searched in the raw (distorted) image, where the highlights are.
    search_radius = disc_radius - 2.0
    found: list[_Highlight | None] = []
    for i in range(n_led):
        try:
            found.append(_highlight(stack[i], disc_center_raw, search_radius,
                                    _STABILITY_THRESHOLDS, saturation_level=saturation_level))
        except FingerpsCalibError as exc:
            problems.append(f"LED {i}: {exc}")
            found.append(None)
    typical = np.median([f.contrast for f in found if f is not None]) if any(found) else 0.0
    disc_area = np.pi * disc_radius**2
    for i, spot in enumerate(found):
        if spot is None:
            continue
        contrast[i] = spot.contrast / spot.shading
        saturated[i] = spot.saturated_px
        if contrast[i] < min_highlight_contrast:
            problems.append(
                f"LED {i}: no highlight: the brightest spot on the sphere stands out only "
                f"{contrast[i]:.1f}x as much as the rest of the sphere (at least "
                f"{min_highlight_contrast:g}x needed); check that LED {i} lights and that its "
                "reflection falls on the sphere; if the whole sphere looks bright, lower the "
                "exposure"
            )
            continue
        if spot.contrast < 0.2 * typical:
            problems.append(
                f"LED {i}: no highlight: the brightest spot on the sphere is only "
                f"{100 * spot.contrast / typical:.0f}% as bright as the other LEDs' "
                f"highlights; check that LED {i} lights and that its reflection falls on the "
                "sphere"
            )
            continue
        if saturation_level is not None and spot.saturated_px > max_saturated_fraction * disc_area:
            problems.append(
                f"LED {i}: the highlight is saturated into a blob of {spot.saturated_px} px "
                f"(at most {max_saturated_fraction * disc_area:.0f} px): its centre is "
                "uncertain; lower the exposure or the LED level"
            )
        u, v = spot.u, spot.v
        uv = _undistort(np.array([[u, v]]), k, distortion)[0]
        highlights[i], residuals[i] = uv, spot.spread_px
        if np.hypot(u - disc_center_raw[0], v - disc_center_raw[1]) > disc_radius - 3.0:
            problems.append(
                f"LED {i}: highlight at ({u:.1f}, {v:.1f}) is at the sphere's limb; move the "
                "sphere nearer the optical axis"
            )
        try:
            directions[i], points[i] = _mirror_ray(uv, center, radius_m, k)
        except FingerpsCalibError as exc:
            problems.append(f"LED {i}: {exc}")
            continue
        if not directions[i, 2] < 0:
            problems.append(
                f"LED {i}: direction {directions[i].round(3).tolist()} points away from the "
                "camera side (z_optical >= 0); the highlight is probably a stray reflection"
            )
        if spot.spread_px > residual_limit_px:
            problems.append(
                f"LED {i}: highlight centroid moves {spot.spread_px:.2f} px with the "
                f"threshold (> {residual_limit_px} px); a second reflection or saturation "
                "bloom is merged with it, clean the sphere or lower the exposure"
            )
    return result(center, fit.rms_residual_px)


def calibrate_lights_orthographic(
    images: np.ndarray, *, mask: np.ndarray | None = None
) -> OrthographicLightResult:
    """Classic chrome-sphere light calibration for an orthographic camera (no intrinsics).

    A circle fitted to the silhouette gives centre c and radius rho; the normal at the
    highlight (u, v) is N = ((u - cu)/rho, -(v - cv)/rho, sqrt(1 - ...)) in the PS frame
    (y up), the view direction V = (0, 0, 1), and l = 2 (N.V) N - V (Eq. 10 with a distant
    camera).

    Parameters
    ----------
    images : (K, H, W) array, any real dtype
    mask : (H, W) bool, optional
        The sphere's pixels (public data sets usually provide one).

    Returns
    -------
    OrthographicLightResult
    """
    stack = np.asarray(images)
    if stack.ndim != 3 or not np.issubdtype(stack.dtype, np.number):
        raise FingerpsCalibError(f"images has shape {stack.shape}, expected (K, H, W)")
    n_led = stack.shape[0]
    directions = np.full((n_led, 3), np.nan)
    highlights = np.full((n_led, 2), np.nan)
    residuals = np.full(n_led, np.nan)
    edges = sphere_edge_points(stack, mask=mask)
    if len(edges) < 20:
        return OrthographicLightResult(
            directions, highlights, np.full(2, np.nan), float("nan"), False,
            ("sphere not found: fewer than 20 edge points; pass the sphere's mask",),
            edge_points_uv=edges, residuals_px=residuals,
        )
    center, rho = _fit_circle(edges)
    edge_rms = float(np.sqrt(np.mean((np.linalg.norm(edges - center, axis=1) - rho) ** 2)))
    problems = []
    for i in range(n_led):
        try:
            found = _highlight(stack[i], center, rho - 2.0, _STABILITY_THRESHOLDS)
        except FingerpsCalibError as exc:
            problems.append(f"LED {i}: {exc}")
            continue
        u, v = found.u, found.v
        highlights[i], residuals[i] = (u, v), found.spread_px
        nx, ny = (u - center[0]) / rho, -(v - center[1]) / rho
        normal = np.array([nx, ny, np.sqrt(max(0.0, 1.0 - nx * nx - ny * ny))])
        normal /= np.linalg.norm(normal)
        directions[i] = 2.0 * normal[2] * normal - np.array([0.0, 0.0, 1.0])
    return OrthographicLightResult(
        directions, highlights, center, float(rho), not problems, tuple(problems),
        edge_rms_px=edge_rms, edge_points_uv=edges, residuals_px=residuals,
    )


# ------------------------------------------------------------------------------ private


def _as_stack(images: np.ndarray, name: str) -> np.ndarray:
    stack = np.asarray(images)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3 or stack.shape[0] < 1 or not np.issubdtype(stack.dtype, np.number):
        raise FingerpsCalibError(
            f"{name} has shape {stack.shape} ({stack.dtype}), expected (K, H, W) or (H, W) "
            "numbers"
        )
    return stack.astype(np.float64)


def _silhouette_contrast(stack: np.ndarray, center: np.ndarray, radius: float) -> float:
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


def _camera_matrix(camera_matrix: np.ndarray) -> np.ndarray:
    k = np.asarray(camera_matrix, dtype=np.float64)
    if k.shape != (3, 3) or not (k[0, 0] > 0 and k[1, 1] > 0) or not np.all(np.isfinite(k)):
        raise FingerpsCalibError(
            f"camera_matrix has shape {k.shape}, expected (3, 3) [[fx,0,cx],[0,fy,cy],[0,0,1]] "
            "finite, with fx, fy > 0; load it with "
            "fingerps_calib.intrinsics.camera_info_yaml.load_camera_info"
        )
    return k


def _rays(uv: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(N, 3) unit rays K^-1 (u, v, 1) of (N, 2) pixels, optical frame."""
    homogeneous = np.column_stack([uv, np.ones(len(uv))])
    rays = np.linalg.solve(k, homogeneous.T).T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit: centre (2,) and radius of (N, 2) points."""
    x, y = points[:, 0], points[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    (bx, by, c), *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    center = np.array([bx / 2, by / 2])
    return center, float(np.sqrt(c + center @ center))


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


def _weighted_centroid(weights: np.ndarray) -> np.ndarray:
    vv, uu = np.nonzero(weights)
    wts = weights[vv, uu]
    return np.array([uu @ wts, vv @ wts]) / wts.sum()


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


def _undistort(uv: np.ndarray, k: np.ndarray, distortion: np.ndarray | None) -> np.ndarray:
    if distortion is None:
        return uv
    points = uv.reshape(-1, 1, 2).astype(np.float64)
    coeffs = np.asarray(distortion, dtype=np.float64).ravel()
    return cv2.undistortPoints(points, k, coeffs, P=k).reshape(-1, 2)
