"""Each LED's specular highlight on the calibration sphere and the light direction it gives
(paper Sec. 3.1, Eq. 10): the highlight's centroid and its stability over thresholds
(`highlight_centroid`, `find_highlight`), and the mirror reflection of the camera ray at
the highlight on the fitted sphere (`light_direction`, `mirror_ray`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.sphere_silhouette import checked_camera_matrix, pixel_rays


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
    found = find_highlight(image, disc_center_uv, disc_radius_px, (relative_threshold,))
    return found.u, found.v


@dataclass(frozen=True)
class Highlight:
    """One highlight: centroid (u, v), its stability and the numbers the checks use."""

    u: float
    v: float
    spread_px: float
    contrast: float        # peak - background (the disc's median)
    shading: float         # brightest part of the disc away from the blob - background
    saturated_px: int      # pixels of the chosen blob at or above the saturation level
    background: float


def find_highlight(
    image: np.ndarray,
    disc_center_uv: np.ndarray,
    disc_radius_px: float,
    thresholds: tuple[float, ...],
    *,
    saturation_level: float | None = None,
) -> Highlight:
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
    return Highlight(float(centroid[0]), float(centroid[1]), spread, peak - background,
                      shading, saturated, background)


def _weighted_centroid(weights: np.ndarray) -> np.ndarray:
    vv, uu = np.nonzero(weights)
    wts = weights[vv, uu]
    return np.array([uu @ wts, vv @ wts]) / wts.sum()


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
    k = checked_camera_matrix(camera_matrix)
    uv = np.asarray(highlight_uv, dtype=np.float64)
    s = np.asarray(sphere_center, dtype=np.float64)
    if uv.shape != (2,) or s.shape != (3,):
        raise FingerpsCalibError(
            f"highlight_uv {uv.shape} / sphere_center {s.shape}: expected (2,) and (3,)"
        )
    return mirror_ray(uv, s, radius_m, k)[0]


def mirror_ray(
    uv: np.ndarray, s: np.ndarray, radius_m: float, k: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction towards the light and the surface point S1 (Eq. 10)."""
    d = pixel_rays(uv[None, :], k)[0]
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
