"""White flat target for the flat-field calibration (paper Sec. 3.2, Eq. 11).

A Lambertian plane perpendicular to the optical axis at ``distance_m``, filling the frame,
albedo ``albedo * (1 + texture_amplitude * t(u, v))`` with t a fixed, seeded, unit-variance
paper texture (white noise blurred over ~1.2 pixels).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.led_field import LedRing
from fingerps_recon.photometric.frames import optical_to_ps

_TEXTURE_SIGMA_PX = 1.2


@dataclass(frozen=True)
class WhiteTarget:
    """Flat white target; the defaults are the rig's.

    Attributes
    ----------
    distance_m : float
        Depth Z of the plane, metres.
    albedo : float
        Mean albedo.
    texture_amplitude : float
        Relative standard deviation of the paper texture.
    seed : int
        Seed of the texture.
    exposure_gain : float
        Fraction of full scale per unit radiance: the target is imaged with a shorter
        exposure than the finger, as a real flat-field calibration would be, so that it
        peaks at ~90 % of full scale instead of saturating.
    """

    distance_m: float = 0.090
    albedo: float = 0.9
    texture_amplitude: float = 0.01
    seed: int = 2
    exposure_gain: float = 1.07

    def albedo_map(self, height: int, width: int) -> np.ndarray:
        """(height, width) float64 albedo of the target seen through each pixel."""
        noise = np.random.default_rng(self.seed).standard_normal((height, width))
        texture = cv2.GaussianBlur(noise, (0, 0), _TEXTURE_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
        texture /= texture.std()
        return self.albedo * (1.0 + self.texture_amplitude * texture)


def render_white_target(
    target: WhiteTarget,
    camera: PinholeCamera,
    leds: LedRing,
    k: int,
    *,
    shading: Callable[..., np.ndarray],
    albedo: np.ndarray | None = None,
) -> np.ndarray:
    """Noiseless radiance image (H, W) float64 of the target under LED ``k``.

    ``shading`` is ``lambertian_shading(normals_ps, lights_ps, *, rho)`` of ``fingerps_recon``;
    ``albedo`` (H, W) is ``target.albedo_map(H, W)``, computed here when not given.
    """
    points = target.distance_m * camera.pixel_rays()
    lights = optical_to_ps(leds.directions_optical(points, k))
    normal = np.array([0.0, 0.0, 1.0])
    rho = target.albedo_map(camera.height, camera.width) if albedo is None else albedo
    return leds.irradiance(points, k) * shading(normal, lights, rho=rho)
