"""One burst in, normals, depth and points out: the reconstruction pipeline without ROS.

Steps: dark-frame subtraction; the lighting field; the finger mask; Lambertian photometric
stereo (paper Eq. 3); optionally the simplified Hanrahan-Krueger solver (Eq. 4-7)
initialised from it (with near lights, at the points of the surface the Lambertian normals
integrate to: ``ReconstructionOptions.refine_near_lights``); ridge enhancement (Eq. 12) on a
copy; integration of the normals into depth, its nearest point at the working distance;
back-projection into points in the optical frame.

Two light models:

- distant lights (the paper's): one direction per LED; the flat field (Eq. 11) divides each
  image by its portion map p_k, and the LEDs' relative intensities scale the rows of L;
- near lights, when the LED positions are known: per pixel, the direction from the point
  where the pixel's ray meets the plane z = working distance to each LED
  (:mod:`fingerps_recon.photometric.pixel_rays`), and per-pixel irradiance from the white target
  (W_k, rebuilt from the portion maps and relative intensities, divided by the target's
  cosine l_k . z) instead of dividing the images. On the simulated rig this halves the HK
  solver's error (bench/bench_recon_accuracy.py). The plane is right at the finger's apex
  only; for the HK solve the directions and irradiance (inverse-square law) are moved to
  the points of the Lambertian normals' depth, which keeps the steep margins' normals
  tilted as much as the skin (bench/bench_normal_tilt.py; issue 23: the rolled print's
  scale).

Views are perspective (per pixel, from the camera matrix) or orthographic (0, 0, 1).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import Enum
from typing import TypeVar

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError, NoFingerError
from fingerps_recon.heap_retention import retain_freed_memory
from fingerps_recon.photometric.finger_mask import finger_mask
from fingerps_recon.photometric.flat_field import flat_field_gain
from fingerps_recon.photometric.hk_solver import (
    HKLighting,
    prepare_hk_lighting,
    prepare_hk_lighting_at_depth,
    solve_hk_prepared,
)
from fingerps_recon.photometric.lambertian import LightRows, light_rows, solve_lambertian
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_recon.photometric.pixel_rays import near_light_directions_ps, view_directions_ps
from fingerps_recon.surface.back_projection import depth_to_points
from fingerps_recon.surface.integration import integrate_normals, integrate_normals_perspective

# Smallest cosine between a near light and the white target's normal used to turn the
# target's brightness into irradiance (a steeper light would amplify the target's noise).
_MIN_TARGET_COSINE = 0.05
# A calibration's light directions must be unit vectors to this tolerance.
_UNIT_TOLERANCE = 1e-3
# Smallest ratio of the light matrix's singular values (smallest / largest) accepted: below
# it the directions are (nearly) coplanar or parallel and the normals are not determined
# (the simulated rig's ratio is 0.31).
_MIN_LIGHT_CONDITION = 0.02
# Relative residual of the integration whose depth the near lights are moved to: the lights
# need the depth to ~0.1 mm, not the ridges (FAST's default is 3e-3).
_RELIGHT_TOL = 3e-2

_T = TypeVar("_T")
# The thread the ridge enhancement runs on beside the integration (serial kernels only:
# numba's parallel kernels are launched from one thread at a time).
_SIDE_THREAD = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fingerps_enhance")

# Every burst allocates and frees the same arrays: freed memory stays in the process, so the
# next burst finds it without page faults (heap_retention).
retain_freed_memory()


class Model(Enum):
    """Reflectance model the normals are solved under."""

    LAMBERT = "lambert"   # Lambertian photometric stereo (paper Eq. 3)
    HK = "hk"             # simplified Hanrahan-Krueger model (paper Eq. 4-7)


class Projection(Enum):
    """Camera model for the view directions, the integration and the points."""

    PERSPECTIVE = "perspective"     # pinhole camera with the camera matrix K
    ORTHOGRAPHIC = "orthographic"   # pixel size = working distance / fx


@dataclass(frozen=True)
class ReconstructionOptions:
    """Options of :func:`reconstruct`; defaults are the simulated rig's."""

    model: Model = Model.LAMBERT
    hk_iterations: int = 5
    """At most this many Levenberg–Marquardt iterations of the HK solver."""
    hk_tol: float = 1e-3
    """The HK iterations stop once one lowers the cost by less than this fraction of it
    (A fitted: a first burst), or once the next steps promise no more than that (A held at
    the previous burst's refit, ``reconstruct_prepared(hk_initial_scale=...)``, as
    recon_node and scan_node do; per chunk of pixels). ``bench/bench_recon_accuracy.py``
    and ``bench/bench_hk_iterations.py`` measure the error against the iterations."""
    projection: Projection = Projection.PERSPECTIVE
    mask_threshold: float = 0.15
    shadow_fraction: float = 0.02
    """Values at or below this fraction of full scale count as shadow (left out)."""
    saturation_fraction: float = 0.995
    """Values at or above this fraction of full scale count as saturated (left out)."""
    enhance: bool = False
    refine_near_lights: bool = True
    """HK model with near lights (LED positions known; perspective): the HK solver's lights
    are moved from the plane z = working distance to the points of the surface the
    Lambertian normals integrate to (:func:`reconstruct_prepared`). The plane's lights tilt
    the normals of the finger's falling margins too little (by ~1 deg at 40-70 deg of
    tilt), which flattens the depth and shrinks its rolled print
    (bench/bench_normal_tilt.py)."""
    w: int = 7
    k: float = 2.5
    working_distance_m: float = 0.09
    """Distance of the finger's nearest point (its apex) from the camera along the optical
    axis, metres: the plane of the near-light model, and the metric scale of the depth (its
    nearest point is put there)."""


@dataclass(frozen=True)
class Reconstruction:
    """Result of :func:`reconstruct`. Normals are unit vectors in the PS frame."""

    normals_ps: np.ndarray          # (H, W, 3) float32, zeros outside ``mask``
    enhanced_ps: np.ndarray | None  # (H, W, 3) float32 after Eq. 12, when asked for
    albedo: np.ndarray              # (H, W) float32, zeros outside ``mask``
    mask: np.ndarray                # (H, W) bool: finger pixels with a valid normal
    depth_m: np.ndarray             # (H, W) float32, optical z in metres, NaN outside
    height_m: np.ndarray            # (H, W) float32, relief towards the camera, NaN outside
    points_optical: np.ndarray      # (N, 3) float32, metres
    point_albedo: np.ndarray        # (N,) float32
    hk_scale: float | None = None   # the HK model's global scale A fitted at the solution
    residual: float | None = None   # Lambertian fit: rms(I - rho n.l) / mean(I), valid pixels
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class PreparedCalibration:
    """What a reconstruction needs that depends only on the calibration, the camera and the
    image size: computed once by :func:`prepare_calibration` when one of them changes, then
    used by every burst (:func:`reconstruct_prepared`).

    Attributes
    ----------
    shape : (H, W)
        Image size it was prepared for.
    camera_matrix : (3, 3) float64
        Intrinsics K, pixels.
    lights : (K, 3) float64 or (K, H, W, 3) float32
        Unit light directions, PS frame: distant lights, or per pixel (near lights).
    light_power : None, (K,) float64 or (K, H, W) float32
        Relative light intensities, or the per-pixel irradiance of the near lights.
    flat_gain : None or (K, H, W) float32
        Distant lights with a flat field: 1 / max(p_k, min portion), the factor of Eq. 11.
    views : (3,) or (H, W, 3) float32
        Unit directions towards the camera, PS frame: orthographic or per pixel.
    lambert_rows : LightRows
        The rows a_k = e_k l_k of the Lambertian solve, made from ``lights`` and
        ``light_power`` (:func:`photometric.lambertian.light_rows`).
    hk_lighting : HKLighting or None
        The lights, views and intensities in the HK solver's layout
        (:func:`photometric.hk_solver.prepare_hk_lighting`), when prepared for the HK model.
    led_positions_optical : None or (K, 3) float64
        The LED positions, metres, optical frame, for near lights (the lights' refinement at
        the surface's points, ``ReconstructionOptions.refine_near_lights``).
    """

    shape: tuple[int, int]
    camera_matrix: np.ndarray
    lights: np.ndarray
    light_power: np.ndarray | None
    flat_gain: np.ndarray | None
    views: np.ndarray
    lambert_rows: LightRows
    hk_lighting: HKLighting | None = None
    led_positions_optical: np.ndarray | None = None

    @property
    def light_count(self) -> int:
        return int(self.lights.shape[0])


def prepare_calibration(
    lights_ps: np.ndarray,
    *,
    camera_matrix: np.ndarray,
    shape: tuple[int, int],
    intensities: np.ndarray | None = None,
    portions: np.ndarray | None = None,
    led_positions_optical: np.ndarray | None = None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> PreparedCalibration:
    """Prepare a calibration for bursts of ``shape`` (see :func:`reconstruct` for the
    parameters): the near-light directions and irradiance, the flat-field gain (Eq. 11) and
    the view directions. Raises ``FingerpsReconError`` on inconsistent or degenerate inputs
    (a camera matrix that is not finite with fx, fy > 0; :func:`check_calibration`;
    :func:`check_portions`; LEDs that do not span 3D from the image centre), so that a bad
    calibration is refused where it is used instead of giving empty reconstructions."""
    h, w = (int(v) for v in shape)
    if h < 1 or w < 1:
        raise FingerpsReconError(f"image size must be at least 1 x 1, got {w} x {h}")
    k_matrix = np.asarray(camera_matrix, dtype=np.float64)
    if (k_matrix.shape != (3, 3) or not np.isfinite(k_matrix).all()
            or not (k_matrix[0, 0] > 0 and k_matrix[1, 1] > 0)
            or not np.array_equal(k_matrix[2], [0.0, 0.0, 1.0])):
        raise FingerpsReconError(
            "the camera matrix must be a finite 3x3 K with fx, fy > 0 and last row 0 0 1 (got "
            f"{np.array2string(k_matrix.reshape(-1), precision=4, max_line_width=10**6)}); "
            "calibrate the camera (camera_info)")
    lights = np.asarray(lights_ps, dtype=np.float64)
    check_calibration(lights, intensities=intensities,
                      led_positions_optical=led_positions_optical)
    count = lights.shape[0]
    if portions is not None:
        if np.shape(portions) != (count, h, w):
            raise FingerpsReconError(
                f"flat-field maps {np.shape(portions)} do not fit the images {(count, h, w)}; "
                "recalibrate the flat field for this camera mode")
        check_portions(portions)
    light_power = None if intensities is None else np.asarray(intensities, dtype=np.float64)
    flat_gain = None
    if led_positions_optical is not None:
        _check_near_lights(np.asarray(led_positions_optical, dtype=np.float64), k_matrix,
                           (h, w), options.working_distance_m)
        lights = near_light_directions_ps(
            led_positions_optical, camera_matrix=k_matrix, shape=(h, w),
            working_distance_m=options.working_distance_m)
        if portions is not None:
            light_power = _irradiance(portions, light_power, lights)
    elif portions is not None:
        flat_gain = flat_field_gain(portions)
    views = (view_directions_ps(k_matrix, (h, w))
             if options.projection is Projection.PERSPECTIVE
             else np.array([0.0, 0.0, 1.0], dtype=np.float32))
    hk_lighting = (prepare_hk_lighting(lights, shape=(h, w), views=views,
                                       intensities=light_power)
                   if options.model is Model.HK else None)
    return PreparedCalibration(
        shape=(h, w), camera_matrix=k_matrix, lights=lights, light_power=light_power,
        flat_gain=flat_gain, views=views,
        lambert_rows=light_rows(lights, shape=(h, w), intensities=light_power),
        hk_lighting=hk_lighting,
        led_positions_optical=(None if led_positions_optical is None else np.array(
            led_positions_optical, dtype=np.float64)))


def reconstruct(
    images: np.ndarray,
    *,
    lights_ps: np.ndarray,
    camera_matrix: np.ndarray,
    full_scale: float,
    intensities: np.ndarray | None = None,
    portions: np.ndarray | None = None,
    dark: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    led_positions_optical: np.ndarray | None = None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> Reconstruction:
    """Reconstruct one burst: :func:`prepare_calibration`, then :func:`reconstruct_prepared`
    (a stream of bursts with one calibration should prepare it once).

    Parameters
    ----------
    images : (K, H, W) uint8/uint16/float
        One image per LED, in the order of ``lights_ps``. Not modified.
    lights_ps : (K, 3) float
        Unit light directions in the PS frame (the light calibration); used as distant
        lights when ``led_positions_optical`` is not given.
    camera_matrix : (3, 3) float
        Intrinsics K, pixels.
    full_scale : float
        The sensor's largest value (255, 4095, ...), for the shadow and saturation levels.
    intensities : (K,) float, optional
        Relative LED intensities (flat-field calibration); all equal when not given.
    portions : (K, H, W) float, optional
        Flat-field portion maps p_k (Eq. 11); no lighting-field correction when not given.
    dark : (H, W), optional
        An all-LEDs-off frame subtracted from every image.
    mask : (H, W) bool, optional
        The object's pixels; found from the images (the finger mask) when not given.
    led_positions_optical : (K, 3) float, optional
        LED positions in metres, optical frame: switches to the near-light model.
    """
    t0 = time.perf_counter()
    if np.ndim(images) != 3:
        raise FingerpsReconError(
            f"a burst must be K images of one size, (K, H, W); got shape {np.shape(images)}")
    prepared = prepare_calibration(
        lights_ps, camera_matrix=camera_matrix, shape=np.shape(images)[1:],
        intensities=intensities, portions=portions,
        led_positions_optical=led_positions_optical, options=options)
    result = reconstruct_prepared(images, prepared, full_scale=full_scale, dark=dark,
                                  mask=mask, options=options)
    result.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
    return result


def reconstruct_prepared(
    images: np.ndarray,
    prepared: PreparedCalibration,
    *,
    full_scale: float,
    dark: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    options: ReconstructionOptions = ReconstructionOptions(),
    hk_initial_scale: float | None = None,
) -> Reconstruction:
    """Reconstruct one burst with a calibration prepared by :func:`prepare_calibration`
    (with the same ``options``); the other parameters as :func:`reconstruct`.
    ``hk_initial_scale``: the HK model's global scale A to hold, e.g. the previous burst's
    ``Reconstruction.hk_scale`` with this calibration: the pixels are then independent and
    solved in one pass (:func:`photometric.hk_solver.solve_hk_prepared` with ``scale``),
    and ``Reconstruction.hk_scale`` is A refitted at this burst's solution, for the next.
    None: A is fitted jointly with the pixels (a first burst)."""
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    stack, brightest = _checked_stack(images, prepared.light_count, full_scale=full_scale,
                                      shadow_fraction=options.shadow_fraction)
    shape = stack.shape[1:]
    if shape != prepared.shape:
        raise FingerpsReconError(
            f"images of {shape[1]} x {shape[0]} px but the calibration was prepared for "
            f"{prepared.shape[1]} x {prepared.shape[0]}: the camera mode changed; "
            "recalibrate (flat field and lights) for this image size")
    if dark is not None and np.shape(dark) != shape:
        raise FingerpsReconError(f"dark frame {np.shape(dark)} differs from the images {shape}")
    if mask is not None and np.shape(mask) != shape:
        raise FingerpsReconError(f"mask {np.shape(mask)} differs from the images {shape}")
    k_matrix = prepared.camera_matrix
    lights, light_power = prepared.lights, prepared.light_power
    # Values at or above ``limit`` are saturated (left out by the solvers and the mask).
    limit = options.saturation_fraction * full_scale
    if dark is not None or prepared.flat_gain is not None:
        # The corrections change the values: a float copy, with the saturated pixels marked
        # above the corrected values' new limit so that they stay excluded.
        saturated = stack >= limit if bool((brightest >= limit).any()) else None
        stack = stack.astype(np.float32)
        if dark is not None:
            stack -= np.asarray(dark, dtype=np.float32)
            np.maximum(stack, 0.0, out=stack)
        if prepared.flat_gain is not None:
            stack *= prepared.flat_gain
        limit = float(stack.max()) + 1.0
        if saturated is not None:
            np.copyto(stack, np.float32(limit), where=saturated)
    # else: the images are used as they are (not copied): the saturation level is the limit.
    if mask is None:
        mask = finger_mask(stack, threshold=options.mask_threshold, saturation_level=limit)
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        raise NoFingerError(
            "no finger in the burst (the mask selects nothing): place a finger in view, or "
            "lower mask_threshold if it is there but dim")
    timings["prepare"] = (time.perf_counter() - t0) * 1e3

    t1 = time.perf_counter()
    shadow_level = options.shadow_fraction * full_scale
    lam = solve_lambertian(stack, prepared.lambert_rows, mask=mask,
                           shadow_level=shadow_level, saturation_level=limit)
    timings["lambert"] = (time.perf_counter() - t1) * 1e3
    valid = lam.valid & mask
    residual = lam.relative_misfit()  # gathered by the solve over the valid pixels' usable values
    normals, albedo, hk_scale = lam.normals, lam.albedo, None
    if options.model is Model.HK:
        t1 = time.perf_counter()
        lighting = prepared.hk_lighting or prepare_hk_lighting(
            lights, shape=shape, views=prepared.views, intensities=light_power)
        if (options.refine_near_lights and prepared.led_positions_optical is not None
                and options.projection is Projection.PERSPECTIVE and lights.ndim == 4
                and valid.any()):
            lighting = _lighting_at_surface(lighting, normals, valid, prepared, options)
            timings["relight"] = (time.perf_counter() - t1) * 1e3
        usable = usable_measurements(stack, shadow_level, limit)
        hk = solve_hk_prepared(stack, lighting, mask=valid, init_normals=normals,
                               init_albedo=albedo, usable=usable, scale=hk_initial_scale,
                               iterations=options.hk_iterations, tol=options.hk_tol)
        normals, albedo, valid = hk.normals, hk.albedo, hk.valid & valid
        hk_scale = hk.refit_scale
        timings["hk"] = (time.perf_counter() - t1) * 1e3
    # Both solvers give float32 normals and albedo that are zero where they are not valid.

    # The ridge enhancement and the depth are independent and each runs on one core: the
    # enhancement runs on a second thread (both release the GIL) while this one integrates.
    enhancing = None
    if options.enhance:
        enhancing = _SIDE_THREAD.submit(_timed, enhance_ridges, normals, w=options.w,
                                        k=options.k, mask=valid)
    t2 = time.perf_counter()
    try:
        depth, height, points, index = _surface(normals, valid, k_matrix, options)
    finally:
        enhanced, enhance_ms = enhancing.result() if enhancing is not None else (None, None)
    timings["depth"] = (time.perf_counter() - t2) * 1e3
    if enhance_ms is not None:
        timings["enhance"] = enhance_ms
    timings["total"] = (time.perf_counter() - t0) * 1e3
    return Reconstruction(
        normals_ps=normals, enhanced_ps=enhanced, albedo=albedo, mask=valid, depth_m=depth,
        height_m=height, points_optical=points, point_albedo=albedo.reshape(-1)[index],
        hk_scale=hk_scale, residual=residual, timings_ms=timings)


def check_calibration(
    lights_ps: np.ndarray,
    *,
    intensities: np.ndarray | None = None,
    led_positions_optical: np.ndarray | None = None,
) -> None:
    """Raise ``FingerpsReconError`` unless a light calibration can determine normals: at
    least 3 finite unit directions (K, 3) that are neither parallel nor coplanar, finite
    positive relative intensities (K,), finite LED positions (K, 3) in metres. Cheap (no
    per-pixel work); :func:`prepare_calibration` calls it, and a node can call it when a
    calibration arrives."""
    lights = np.asarray(lights_ps, dtype=np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3 or lights.shape[0] < 3:
        raise FingerpsReconError(
            f"light directions must be (K, 3) with K >= 3, got {lights.shape}; recalibrate "
            "the lights")
    count = lights.shape[0]
    if not np.isfinite(lights).all():
        raise FingerpsReconError(
            "light directions contain NaN or infinite values; recalibrate the lights")
    norms = np.linalg.norm(lights, axis=1)
    off = np.flatnonzero(np.abs(norms - 1.0) > _UNIT_TOLERANCE)
    if off.size:
        raise FingerpsReconError(
            f"light direction(s) of LED {', '.join(str(int(k)) for k in off)} are not unit "
            f"vectors (lengths {', '.join(f'{norms[k]:.3g}' for k in off)}); recalibrate the "
            "lights")
    _check_conditioned(lights, "light directions")
    if intensities is not None:
        power = np.asarray(intensities, dtype=np.float64)
        if power.shape != (count,) or not np.isfinite(power).all() or not np.all(power > 0):
            raise FingerpsReconError(
                f"relative intensities must be {count} finite values > 0, got "
                f"{np.array2string(power, precision=3, max_line_width=10**6)}; recalibrate "
                "the flat field")
    if led_positions_optical is not None:
        leds = np.asarray(led_positions_optical, dtype=np.float64)
        if leds.shape != (count, 3) or not np.isfinite(leds).all():
            raise FingerpsReconError(
                f"LED positions must be {count} finite points (K, 3) in metres, got shape "
                f"{leds.shape}{'' if leds.shape != (count, 3) else ' with NaN or inf'}; "
                "recalibrate the lights")


def check_portions(portions: np.ndarray) -> None:
    """Raise ``FingerpsReconError`` unless flat-field portion maps (K, H, W) are finite,
    non-negative and each has a positive maximum (paper Eq. 11: p_k in (0, 1]). One pass
    over the maps: call it once per flat field, not per burst."""
    p = np.asarray(portions)
    if p.ndim != 3 or min(p.shape) < 1:
        raise FingerpsReconError(
            f"flat-field maps must be (K, H, W) with H, W >= 1, got {p.shape}")
    flat = p.reshape(p.shape[0], -1)
    if not np.isfinite(flat).all():
        raise FingerpsReconError(
            "flat-field maps contain NaN or infinite values; recalibrate the flat field")
    low, high = flat.min(axis=1), flat.max(axis=1)
    bad = np.flatnonzero((low < 0) | (high <= 0))
    if bad.size:
        raise FingerpsReconError(
            f"flat-field map(s) of LED {', '.join(str(int(k)) for k in bad)} are negative or "
            "all zero (portions must be in (0, 1]); recalibrate the flat field")


def _check_conditioned(lights: np.ndarray, what: str) -> None:
    """Raise unless the (K, 3) unit directions span 3D (not parallel, not coplanar)."""
    singular = np.linalg.svd(lights, compute_uv=False)
    if not singular[-1] > _MIN_LIGHT_CONDITION * singular[0]:
        raise FingerpsReconError(
            f"{what} are parallel or coplanar (singular values "
            f"{', '.join(f'{v:.3g}' for v in singular)}): they cannot determine a normal; "
            "recalibrate the lights (every LED lit, the sphere in view)")


def _check_near_lights(leds: np.ndarray, camera_matrix: np.ndarray, shape: tuple[int, int],
                       working_distance_m: float) -> None:
    """Raise unless the LEDs light the plane z = working distance from its camera side and
    their directions at the image centre span 3D (cheap: one point, not every pixel)."""
    if not working_distance_m > 0:
        raise FingerpsReconError(f"working distance must be > 0 m, got {working_distance_m}")
    behind = np.flatnonzero(leds[:, 2] >= working_distance_m)
    if behind.size:
        raise FingerpsReconError(
            f"LED(s) {', '.join(str(int(k)) for k in behind)} lie at or beyond the working "
            f"distance {working_distance_m:g} m "
            f"(z {', '.join(f'{leds[k, 2]:.3g}' for k in behind)} m): they cannot light the "
            "finger's side facing the camera; recalibrate the lights or set working_distance")
    centre = np.linalg.solve(camera_matrix, [(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
    towards = leds - centre * working_distance_m
    _check_conditioned(towards / np.linalg.norm(towards, axis=1, keepdims=True),
                       "the LEDs' directions at the image centre")


def usable_measurements(stack: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The (K, H, W) bool map of the measurements the solvers use: lo < I < hi (not
    shadowed, not saturated). Integer images are compared with the equivalent integer
    bounds (lo < I <=> I >= floor(lo) + 1; I < hi <=> I <= ceil(hi) - 1), in their own
    dtype: numpy would otherwise convert every value to float64 first."""
    if stack.dtype.kind != "u":
        return (stack > lo) & (stack < hi)
    top = int(np.iinfo(stack.dtype).max)
    first, last = max(math.floor(lo) + 1, 0), min(math.ceil(hi) - 1, top)
    if first > last:
        return np.zeros(stack.shape, dtype=bool)
    kind = stack.dtype.type
    return (stack >= kind(first)) & (stack <= kind(last))


def _timed(fn: Callable[..., _T], *args: object, **kwargs: object) -> tuple[_T, float]:
    """``fn(*args, **kwargs)`` and the milliseconds it took."""
    start = time.perf_counter()
    value = fn(*args, **kwargs)
    return value, (time.perf_counter() - start) * 1e3


def _irradiance(portions: np.ndarray, intensities: np.ndarray | None,
                lights: np.ndarray) -> np.ndarray:
    """Per-pixel irradiance E_k (K, H, W) of each LED from the white target: W_k rebuilt from
    the portion maps (p_k = W_k / max W_k) and the relative intensities (mean W_k over the
    brightest LED's), divided by the target's cosine l_k . z (it faces the camera)."""
    p = np.asarray(portions, dtype=np.float32)
    relative = np.ones(len(p)) if intensities is None else intensities
    white = p * (relative / p.reshape(len(p), -1).mean(axis=1))[:, None, None].astype(np.float32)
    return white / np.maximum(lights[..., 2], _MIN_TARGET_COSINE)


def _lighting_at_surface(lighting: HKLighting, normals: np.ndarray, valid: np.ndarray,
                         prepared: PreparedCalibration, options: ReconstructionOptions
                         ) -> HKLighting:
    """The HK solver's near lights moved from the plane z = working distance to the points
    of the surface that ``normals`` (the Lambertian solution) integrate to, the nearest at
    the working distance (:func:`photometric.hk_solver.prepare_hk_lighting_at_depth`).

    The plane's lights are right at the apex only: where the finger falls away from it
    (4 mm at 60 deg of tilt) each LED is seen ~1 deg nearer the optical axis than on the
    plane, which tilts the solved normals of the margins too little and flattens the depth
    and its rolled print. The Lambertian depth is too flat as well (its normals ~4 deg too
    little tilted at the margins: ~0.5 mm of depth), but that moves the lights by ~0.1 deg,
    a tenth of the plane's error (bench/bench_normal_tilt.py). So the depth is integrated
    loosely (``_RELIGHT_TOL``) at half resolution (:func:`_half_resolution_depth`: it
    moves the lights by ~0.01 deg at the steepest margin) and each pixel takes its block's."""
    depth = _half_resolution_depth(normals, valid, prepared.camera_matrix, options)
    return prepare_hk_lighting_at_depth(
        lighting, depth, mask=valid, led_positions_optical=prepared.led_positions_optical,
        plane_power=prepared.light_power, working_distance_m=options.working_distance_m)


def _half_resolution_depth(normals: np.ndarray, valid: np.ndarray, k_matrix: np.ndarray,
                           options: ReconstructionOptions) -> np.ndarray:
    """(H, W) float32 depth of the normals integrated on blocks of 2 x 2 pixels (their mean
    normal; a block is on the finger where one of its pixels is), the nearest point at the
    working distance, each pixel given its block's depth (the last row and column of an odd
    size their neighbours'); NaN off the finger's blocks."""
    h, w = valid.shape
    h2, w2 = h // 2, w // 2
    if h2 < 2 or w2 < 2:
        return np.full((h, w), np.nan, np.float32)
    inside = cv2.resize(valid[: 2 * h2, : 2 * w2].view(np.uint8), (w2, h2),
                        interpolation=cv2.INTER_AREA) > 0
    mean = cv2.resize(np.ascontiguousarray(normals[: 2 * h2, : 2 * w2]), (w2, h2),
                      interpolation=cv2.INTER_AREA)  # zeros off the finger: shorter, same way
    half = k_matrix.copy()
    half[:2] /= 2.0
    half[:2, 2] -= 0.25  # pixel (u, v) of the blocks is pixel (2 u + 1/2, 2 v + 1/2)
    depth2 = _nearest_at(integrate_normals_perspective(
        mean, mask=inside, camera_matrix=half, working_distance_m=options.working_distance_m,
        tol=_RELIGHT_TOL), options.working_distance_m)
    depth = np.empty((h, w), np.float32)
    depth[: 2 * h2, : 2 * w2] = np.repeat(np.repeat(depth2, 2, axis=0), 2, axis=1)
    if h % 2:
        depth[-1] = depth[-2]
    if w % 2:
        depth[:, -1] = depth[:, -2]
    return depth


def _surface(normals: np.ndarray, valid: np.ndarray, k_matrix: np.ndarray,
             options: ReconstructionOptions) -> tuple[np.ndarray, ...]:
    """Depth, height, points and their pixel index, under the options' projection:
    perspective, the finger's nearest point at the working distance (:func:`_nearest_at`);
    orthographic, the height of zero mean (no scale depends on it)."""
    distance = options.working_distance_m
    if options.projection is Projection.PERSPECTIVE:
        depth = _nearest_at(integrate_normals_perspective(
            normals, mask=valid, camera_matrix=k_matrix, working_distance_m=distance),
            distance)
        points, index = depth_to_points(depth, valid, camera_matrix=k_matrix)
        return depth, (distance - depth).astype(np.float32), points, index
    pixel_size = distance / float(k_matrix[0, 0])
    height = integrate_normals(normals, mask=valid, pixel_size_m=pixel_size)
    depth = (distance - height.astype(np.float64)).astype(np.float32)
    index = np.flatnonzero(valid & np.isfinite(height))
    v, u = np.divmod(index, valid.shape[1])
    points = np.stack([(u - k_matrix[0, 2]) * pixel_size, (v - k_matrix[1, 2]) * pixel_size,
                       depth.reshape(-1)[index]], axis=1).astype(np.float32)
    return depth, height, points, index


def _nearest_at(depth: np.ndarray, distance: float) -> np.ndarray:
    """``depth`` (H, W) float32 (NaN off the finger) scaled in place so that its nearest
    point is at ``distance``. The normals fix a perspective depth up to a scale (the
    log-depth's offset, :func:`surface.integration.integrate_normals_perspective`, which
    puts the geometric mean at the working distance); the working distance is where the
    finger's nearest point (its apex) is held, the plane the near lights are computed for
    (:mod:`photometric.pixel_rays`). Putting the mean there instead would bring a finger,
    whose margins fall away by several millimetres, ~2 % too near and shrink every length
    on it (its rolled print) by as much (bench/bench_normal_tilt.py)."""
    nearest = float(np.fmin.reduce(depth, axis=None))  # NaN ignored; NaN when all are
    if math.isfinite(nearest):
        depth *= np.float32(distance / nearest)
    return depth


# Image dtypes used as they are (the solvers read them; integers are exact in float32):
# the two the kernel warm-up compiles (photometric.kernel_warm_up), so that no burst waits
# for a compilation; others (uint16 too) become float32.
_NATIVE_IMAGES = (np.uint8, np.float32)


def _checked_stack(images: np.ndarray, light_count: int, *, full_scale: float,
                   shadow_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The burst as a (K, H, W) uint8 or float32 array (the input itself when it is one of
    those, else a float32 copy; never modified) and each image's largest value (K,),
    or a FingerpsReconError saying what is wrong with it (shape, count, NaN, dark images).
    Integers need no finiteness test; floats are tested by their per-image maximum (NaN
    and +inf show there) and minimum (-inf): reductions without temporaries."""
    stack = np.asarray(images)
    if stack.ndim != 3:
        raise FingerpsReconError(
            f"a burst must be K images of one size, (K, H, W); got shape {stack.shape}")
    if min(stack.shape[1:]) < 1:
        raise FingerpsReconError(
            f"the images are {stack.shape[2]} x {stack.shape[1]} px: empty; check the camera")
    if stack.shape[0] != light_count:
        raise FingerpsReconError(
            f"{stack.shape[0]} images (shape {stack.shape}) but {light_count} light directions: "
            "give one image per calibrated LED (recalibrate if the LED count changed)")
    if stack.dtype not in _NATIVE_IMAGES:
        stack = stack.astype(np.float32)
    flat = stack.reshape(stack.shape[0], -1)
    brightest = flat.max(axis=1)
    if stack.dtype.kind == "f" and not (np.isfinite(brightest).all()
                                        and np.isfinite(flat.min(axis=1)).all()):
        raise FingerpsReconError("the images contain NaN or infinite values; check the camera")
    dark = np.flatnonzero(brightest <= shadow_fraction * full_scale)
    if dark.size:
        raise FingerpsReconError(
            f"image(s) of LED {', '.join(str(int(k)) for k in dark)} are dark (nothing above "
            f"{shadow_fraction:.0%} of full scale {full_scale:g}): check that the LED works "
            "and the finger is in view")
    return stack, brightest
