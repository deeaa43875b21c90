"""Reflectance of the simulated finger's skin: the HK model or a Lambertian surface.

Both come from ``fingerps_recon`` (``hk_model.hk_reflectance``, paper Eq. 4;
``lambertian.lambertian_shading``), so the rig renders with the forward models the
reconstruction inverts.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.hk_model import FINGER, SkinParams, hk_reflectance
from fingerps_recon.photometric.lambertian import lambertian_shading


class Reflectance(Enum):
    """Reflectance model of the finger's skin."""

    HK = "hk"
    LAMBERT = "lambert"


@dataclass(frozen=True)
class SkinReflectance:
    """How the skin reflects: ``model``, and for HK the global scale ``hk_scale`` (A of the
    single-scattering term, paper Eq. 4) and the skin constants ``hk_params``. The defaults
    are the paper's finger (``fingerps_recon.photometric.hk_model.FINGER``) under HK.
    """

    model: Reflectance = Reflectance.HK
    hk_scale: float = 45.0
    hk_params: SkinParams = FINGER

    def shading(
        self,
        normals_ps: np.ndarray,
        lights_ps: np.ndarray,
        points_optical: np.ndarray,
        *,
        rho: np.ndarray,
    ) -> np.ndarray:
        """Reflected radiance (N,) per unit irradiance of surface points.

        Parameters
        ----------
        normals_ps, lights_ps : (N, 3) float64
            Unit normals and unit directions towards the light, PS frame.
        points_optical : (N, 3) float64
            The points, metres, optical frame (the view direction is towards the camera
            centre, the origin).
        rho : (N,) float64
            Albedo of the Lambertian term.
        """
        if self.model is Reflectance.HK:
            views = optical_to_ps(
                -points_optical / np.linalg.norm(points_optical, axis=-1, keepdims=True)
            )
            return hk_reflectance(
                normals_ps, lights_ps, views, rho=rho, scale=self.hk_scale,
                params=self.hk_params,
            )
        return lambertian_shading(normals_ps, lights_ps, rho=rho)
