"""Light directions from images of a shiny sphere of known radius (paper Sec. 3.1, Eq. 8-10).

Geometry in the camera optical frame (x right, y down, z forward, metres), camera centre
at the origin; the ray through pixel (u, v) is K^-1 (u, v, 1), i.e. (u - cx, v - cy, f)
when fx = fy = f. Pixel coordinates (u, v) are ideal (undistorted) ones unless a function
takes ``distortion``. See ../shared/paper/NOTES.md Sec. 3.1.

Steps (`calibrate_lights`):

1. `sphere_silhouette.sphere_edge_points`: sub-pixel silhouette points of the sphere.
2. `sphere_silhouette.fit_sphere_center`: the sphere centre S from the tangent rays (Eq. 8, 9).
3. `sphere_highlight.highlight_centroid`: the specular highlight of each LED.
4. `sphere_highlight.light_direction`: the mirror reflection at the highlight (Eq. 10).

Here: the steps run on a set of images, with the checks that accept or refuse the result
(each with a named threshold).

`calibrate_lights_orthographic` is the classic chrome-sphere method for public data sets
without intrinsics (orthographic camera, directions in the PS frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.sphere_highlight import Highlight, find_highlight, mirror_ray
from fingerps_calib.lights.sphere_silhouette import (
    check_radius,
    checked_camera_matrix,
    fit_circle,
    fit_sphere_center,
    silhouette_contrast,
    sphere_edge_points,
    undistort_points,
)
from fingerps_recon.photometric.frames import optical_to_ps

#: Gaussian smoothing (pixels) of the silhouette search, tried in turn while the sphere fit's
#: rms exceeds the limit: noisy images need more. A real misfit (a wrong camera matrix, an
#: occluded or out-of-round silhouette) stays above the limit at every smoothing.
_EDGE_SMOOTHING_PX = (0.5, 1.0, 1.5, 2.0)

# The acceptance checks of `calibrate_lights` (besides its parameters' limits):
#: Fewest silhouette points a sphere is looked for in.
MIN_EDGE_POINTS = 20
#: Least step across the found outline, in units of the noise, for it to be the sphere's
#: silhouette (`silhouette_contrast`: ~12 on the simulated rig, ~3 with four times its read
#: noise, 0 for an empty view).
MIN_SILHOUETTE_CONTRAST = 2.0
#: A silhouette fitting worse than this many times ``edge_rms_limit_px`` is not a sphere.
NOT_A_SPHERE_RMS_FACTOR = 5.0
#: Least fraction of the outline the edge points must cover.
MIN_OUTLINE_FRACTION = 0.5
#: Pixels between the silhouette and the image border for the sphere to be seen whole.
BORDER_MARGIN_PX = 1.0
#: The highlight is searched this many pixels inside the silhouette, and refused when
#: within ``LIMB_MARGIN_PX`` of it (at the limb the mirror ray is grazing).
SEARCH_MARGIN_PX = 2.0
LIMB_MARGIN_PX = 3.0
#: Least highlight peak of an LED relative to the median of the LEDs' peaks.
MIN_RELATIVE_HIGHLIGHT = 0.2

#: Relative thresholds at which the highlight centroid is recomputed to measure its
#: stability (`LightCalibrationResult.residuals_px`); the middle one gives the centroid.
_STABILITY_THRESHOLDS = (0.3, 0.5, 0.7)



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
    k = checked_camera_matrix(camera_matrix)
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
        if len(raw_edges) < MIN_EDGE_POINTS:
            problems.append(
                f"sphere not found: fewer than {MIN_EDGE_POINTS} points of its silhouette; put "
                "the whole sphere in view against a dark background (or pass a mask)"
            )
            return result(np.full(3, np.nan), float("nan"))
        edges = undistort_points(raw_edges, k, distortion)
        fit = fit_sphere_center(edges, camera_matrix=k, radius_m=radius_m)
        if fit.rms_residual_px <= edge_rms_limit_px:
            break
    center = fit.center_optical_m
    disc_center_raw, disc_radius = fit_circle(raw_edges)
    step = silhouette_contrast(stack, disc_center_raw, disc_radius)
    if mask is None and not step >= MIN_SILHOUETTE_CONTRAST:
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
    if fit.rms_residual_px > NOT_A_SPHERE_RMS_FACTOR * edge_rms_limit_px:
        problems.append(
            f"the object in view is not the sphere: its silhouette fits a sphere to "
            f"{fit.rms_residual_px:.1f} px rms (at most {edge_rms_limit_px} px); put the "
            "sphere in view, alone, against a dark background (if it is the sphere, check "
            "the camera matrix)"
        )
        return result(center, fit.rms_residual_px)
    if require_whole_sphere:
        sides = [name for name, outside in (
            ("left", disc_center_raw[0] - disc_radius < BORDER_MARGIN_PX),
            ("right", disc_center_raw[0] + disc_radius > w - 1.0 - BORDER_MARGIN_PX),
            ("top", disc_center_raw[1] - disc_radius < BORDER_MARGIN_PX),
            ("bottom", disc_center_raw[1] + disc_radius > h - 1.0 - BORDER_MARGIN_PX),
        ) if outside]
        if sides:
            problems.append(
                f"the sphere is cut by the image border ({', '.join(sides)}): move it towards "
                "the middle of the view so that all of it is seen"
            )
    expected = np.pi * 2 * fit.silhouette_radius_px
    if len(raw_edges) < MIN_OUTLINE_FRACTION * expected:
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
    search_radius = disc_radius - SEARCH_MARGIN_PX
    found: list[Highlight | None] = []
    for i in range(n_led):
        try:
            found.append(find_highlight(stack[i], disc_center_raw, search_radius,
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
        if spot.contrast < MIN_RELATIVE_HIGHLIGHT * typical:
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
        uv = undistort_points(np.array([[u, v]]), k, distortion)[0]
        highlights[i], residuals[i] = uv, spot.spread_px
        if np.hypot(u - disc_center_raw[0], v - disc_center_raw[1]) > disc_radius - LIMB_MARGIN_PX:
            problems.append(
                f"LED {i}: highlight at ({u:.1f}, {v:.1f}) is at the sphere's limb; move the "
                "sphere nearer the optical axis"
            )
        try:
            directions[i], points[i] = mirror_ray(uv, center, radius_m, k)
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
    center, rho = fit_circle(edges)
    edge_rms = float(np.sqrt(np.mean((np.linalg.norm(edges - center, axis=1) - rho) ** 2)))
    problems = []
    for i in range(n_led):
        try:
            found = find_highlight(stack[i], center, rho - 2.0, _STABILITY_THRESHOLDS)
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
