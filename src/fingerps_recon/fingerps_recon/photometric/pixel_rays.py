"""Per-pixel geometry of a pinhole camera: view directions and near-light directions.

The paper assumes distant lights and an orthographic view. At fingertip distances neither
holds: with LEDs 40 mm off axis at 90 mm, the direction to an LED changes by up to ~6°
across a 20 mm field, and the view direction by up to ~6° too. These functions give the
per-pixel directions for a surface assumed to lie on the plane z = working distance
(optical frame), which removes most of that error without knowing the shape first.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.frames import optical_to_ps


def checked_camera_matrix(camera_matrix: np.ndarray) -> np.ndarray:
    """``camera_matrix`` as a (3, 3) float64 K, or a one-line FingerpsReconError if it is not
    a finite 3x3 matrix with fx, fy > 0."""
    k = np.asarray(camera_matrix, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise FingerpsReconError(
            f"camera_matrix must be a finite 3x3 intrinsic matrix with fx, fy > 0, got "
            f"{k.tolist()}; calibrate the camera (calibrate_camera) or fix camera_info")
    return k


def pixel_rays_optical(camera_matrix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float64 rays K^-1 (u, v, 1) through each pixel centre, optical frame (z = 1)."""
    k = checked_camera_matrix(camera_matrix)
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    return pixels @ np.linalg.inv(k).T


def view_directions_ps(camera_matrix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float32 unit directions from each pixel's surface point towards the camera,
    PS frame (perspective view; (0, 0, 1) on the optical axis)."""
    return _cached_views(_key(camera_matrix), tuple(shape))


def near_light_directions_ps(
    led_positions_optical: np.ndarray,
    *,
    camera_matrix: np.ndarray,
    shape: tuple[int, int],
    working_distance_m: float,
) -> np.ndarray:
    """(K, H, W, 3) float32 unit directions from each pixel's surface point towards each LED,
    PS frame, for a surface on the plane z = ``working_distance_m`` (optical frame)."""
    leds = np.asarray(led_positions_optical, dtype=np.float64)
    if leds.ndim != 2 or leds.shape[1] != 3 or not np.isfinite(leds).all():
        raise FingerpsReconError(
            f"LED positions must be a finite (K, 3) array in metres, got shape {leds.shape}")
    if not working_distance_m > 0:
        raise FingerpsReconError(f"working distance must be > 0 m, got {working_distance_m}")
    return _cached_lights(leds.tobytes(), leds.shape[0], _key(camera_matrix), tuple(shape),
                          float(working_distance_m))


def _key(camera_matrix: np.ndarray) -> bytes:
    return np.asarray(camera_matrix, dtype=np.float64).tobytes()


@lru_cache(maxsize=4)
def _cached_views(k_bytes: bytes, shape: tuple[int, int]) -> np.ndarray:
    rays = pixel_rays_optical(np.frombuffer(k_bytes).reshape(3, 3), shape)
    towards_camera = -rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    views = optical_to_ps(towards_camera).astype(np.float32)
    views.setflags(write=False)
    return views


@lru_cache(maxsize=4)
def _cached_lights(led_bytes: bytes, count: int, k_bytes: bytes, shape: tuple[int, int],
                   working_distance_m: float) -> np.ndarray:
    leds = np.frombuffer(led_bytes).reshape(count, 3)
    points = pixel_rays_optical(np.frombuffer(k_bytes).reshape(3, 3), shape) * working_distance_m
    px, py, pz = (np.ascontiguousarray(points[..., i]) for i in range(3))
    lights = np.empty((count, *shape, 3), dtype=np.float32)
    for k, (lx, ly, lz) in enumerate(leds):  # one LED at a time: planes, no (K, H, W, 3) temp
        dx, dy, dz = lx - px, ly - py, lz - pz
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        # optical -> PS frame (x, -y, -z), as frames.optical_to_ps
        lights[k, ..., 0] = dx * inv
        lights[k, ..., 1] = -(dy * inv)
        lights[k, ..., 2] = -(dz * inv)
    lights.setflags(write=False)
    return lights
