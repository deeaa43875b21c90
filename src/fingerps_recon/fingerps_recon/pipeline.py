"""One burst in, normals, depth and points out: the reconstruction pipeline without ROS.

Steps: dark-frame subtraction, flat-field correction (paper Eq. 11), the finger mask,
Lambertian photometric stereo (paper Eq. 3), optional ridge enhancement (Eq. 12) on a copy,
integration of the normals into depth, back-projection into points in the optical frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.finger_mask import finger_mask
from fingerps_recon.flat_field import apply_flat_field
from fingerps_recon.integration import depth_to_points, height_to_distance, integrate_normals
from fingerps_recon.lambertian import solve_lambertian
from fingerps_recon.normal_transform import enhance_ridges


class Model(Enum):
    """Reflectance model the normals are solved under."""

    LAMBERT = "lambert"   # Lambertian photometric stereo (paper Eq. 3)
    HK = "hk"             # simplified Hanrahan-Krueger model (paper Eq. 4-7)


@dataclass(frozen=True)
class ReconstructionOptions:
    """Options of :func:`reconstruct`; defaults are the simulated rig's."""

    model: Model = Model.LAMBERT
    hk_iterations: int = 10
    mask_threshold: float = 0.15
    shadow_fraction: float = 0.02
    """Values at or below this fraction of full scale count as shadow (left out)."""
    saturation_fraction: float = 0.995
    """Values at or above this fraction of full scale count as saturated (left out)."""
    enhance: bool = False
    w: int = 7
    k: float = 2.5
    working_distance_m: float = 0.09


@dataclass(frozen=True)
class Reconstruction:
    """Result of :func:`reconstruct`. Normals are unit vectors in the PS frame."""

    normals_ps: np.ndarray          # (H, W, 3) float32, zeros outside ``mask``
    enhanced_ps: np.ndarray | None  # (H, W, 3) float32 after Eq. 12, when asked for
    albedo: np.ndarray              # (H, W) float32
    mask: np.ndarray                # (H, W) bool: finger pixels with a valid normal
    depth_m: np.ndarray             # (H, W) float32, optical z in metres, NaN outside
    points_optical: np.ndarray      # (N, 3) float32, metres
    point_albedo: np.ndarray        # (N,) float32
    timings_ms: dict[str, float] = field(default_factory=dict)


def reconstruct(
    images: np.ndarray,
    *,
    lights_ps: np.ndarray,
    camera_matrix: np.ndarray,
    full_scale: float,
    intensities: np.ndarray | None = None,
    portions: np.ndarray | None = None,
    dark: np.ndarray | None = None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> Reconstruction:
    """Reconstruct one burst.

    Parameters
    ----------
    images : (K, H, W) uint8/uint16/float
        One image per LED, in the order of ``lights_ps``.
    lights_ps : (K, 3) float
        Unit light directions in the PS frame (from the light calibration).
    camera_matrix : (3, 3) float
        Intrinsics K, pixels.
    full_scale : float
        The sensor's largest value (255, 4095, ...), for the shadow and saturation levels.
    intensities : (K,) float, optional
        Relative LED intensities (flat-field calibration); all equal when not given.
    portions : (K, H, W) float, optional
        Flat-field portion maps p_k (Eq. 11); no correction when not given.
    dark : (H, W), optional
        An all-LEDs-off frame subtracted from every image.
    """
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    stack = _checked_stack(images, len(lights_ps), full_scale=full_scale,
                           shadow_fraction=options.shadow_fraction)
    saturated = stack >= options.saturation_fraction * full_scale
    if dark is not None:
        if np.shape(dark) != stack.shape[1:]:
            raise FingerpsReconError(
                f"dark frame {np.shape(dark)} differs from the images {stack.shape[1:]}")
        stack = np.clip(stack - np.asarray(dark, dtype=np.float32), 0.0, None)
    if portions is not None:
        stack = apply_flat_field(stack, portions)
    # Saturated pixels stay excluded after correction: mark them above the new limit.
    limit = float(stack.max()) + 1.0
    stack[saturated] = limit
    mask = finger_mask(np.where(saturated, 0.0, stack), threshold=options.mask_threshold)
    if not mask.any():
        raise FingerpsReconError(
            "no finger in the burst (the mask selects nothing): place a finger in view, or "
            "lower mask_threshold if it is there but dim")
    timings["prepare"] = (time.perf_counter() - t0) * 1e3

    t1 = time.perf_counter()
    lights = np.asarray(lights_ps, dtype=np.float64)
    shadow_level = options.shadow_fraction * full_scale
    lam = solve_lambertian(stack, lights, intensities=intensities, mask=mask,
                           shadow_level=shadow_level, saturation_level=limit)
    timings["lambert"] = (time.perf_counter() - t1) * 1e3
    valid = lam.valid & mask
    normals, albedo = lam.normals, lam.albedo
    if options.model is Model.HK:
        from fingerps_recon.hk_solver import solve_hk

        t1 = time.perf_counter()
        usable = (stack > shadow_level) & (stack < limit)
        hk = solve_hk(stack, lights, mask=valid, init_normals=normals, init_albedo=albedo,
                      intensities=intensities, usable=usable,
                      iterations=options.hk_iterations)
        normals, albedo, valid = hk.normals, hk.albedo, hk.valid & valid
        timings["hk"] = (time.perf_counter() - t1) * 1e3
    normals = np.where(valid[..., None], normals, 0.0).astype(np.float32)

    enhanced = None
    if options.enhance:
        enhanced = enhance_ridges(normals, w=options.w, k=options.k, mask=valid)

    t2 = time.perf_counter()
    fx = float(camera_matrix[0, 0])
    height = integrate_normals(normals, mask=valid,
                               pixel_size_m=options.working_distance_m / fx)
    depth = height_to_distance(height, working_distance_m=options.working_distance_m)
    points, index = depth_to_points(depth, valid, camera_matrix=camera_matrix)
    timings["depth"] = (time.perf_counter() - t2) * 1e3
    timings["total"] = (time.perf_counter() - t0) * 1e3
    albedo = np.where(valid, albedo, 0.0).astype(np.float32)
    return Reconstruction(
        normals_ps=normals, enhanced_ps=enhanced, albedo=albedo, mask=valid, depth_m=depth,
        points_optical=points, point_albedo=albedo.reshape(-1)[index], timings_ms=timings)


def _checked_stack(images: np.ndarray, light_count: int, *, full_scale: float,
                   shadow_fraction: float) -> np.ndarray:
    """The burst as a new (K, H, W) float32 array, or a FingerpsReconError saying what is
    wrong with it (shape, count, NaN, dark images)."""
    stack = np.array(images, dtype=np.float32)
    if stack.ndim != 3:
        raise FingerpsReconError(
            f"a burst must be K images of one size, (K, H, W); got shape {stack.shape}")
    if stack.shape[0] != light_count:
        raise FingerpsReconError(
            f"{stack.shape[0]} images (shape {stack.shape}) but {light_count} light directions: "
            "give one image per calibrated LED (recalibrate if the LED count changed)")
    if not np.isfinite(stack).all():
        raise FingerpsReconError("the images contain NaN or infinite values; check the camera")
    brightest = stack.reshape(stack.shape[0], -1).max(axis=1)
    dark = np.flatnonzero(brightest <= shadow_fraction * full_scale)
    if dark.size:
        raise FingerpsReconError(
            f"image(s) of LED {', '.join(str(int(k)) for k in dark)} are dark (nothing above "
            f"{shadow_fraction:.0%} of full scale {full_scale:g}): check that the LED works "
            "and the finger is in view")
    return stack
