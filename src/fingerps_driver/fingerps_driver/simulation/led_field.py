"""Near point-light LEDs with an anisotropic emission lobe, and their emitting discs.

Each LED k sits at ``positions_optical[k]`` (metres, optical frame) and emits with the
radiant intensity of a cos^m lobe about its axis ``axes_optical[k]``:

    I_k(theta) = power_k * d_ref**2 * max(cos theta, 0)**m_k

so the irradiance factor (the "lighting field" the flat-field calibration of paper Eq. 11
measures) at a point P at distance d from the LED is

    E_k(P) = power_k * (d_ref / d)**2 * max(cos theta, 0)**m_k,   cos theta = a_k . (P - L_k) / d.

Units: E = 1 is the irradiance of a power-1 LED at distance ``d_ref`` on its axis; a
Lambertian surface of albedo rho facing it then has radiance rho (the factor 1/pi is dropped
throughout the simulation, consistently for diffuse and specular terms).

Seen in a mirror, the LED is a flat disc of radius ``disc_radius_m`` facing along its axis.
Its radiance in the same units is power_k * (d_ref / r_disc)**2 * cos**(m_k - 1) theta inside
the disc, with a soft rim (tanh profile of width ``rim_fraction * r_disc``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class LedRing:
    """The LEDs of the rig.

    Attributes
    ----------
    positions_optical : (K, 3) float64
        LED centres, metres, optical frame (camera centre at the origin).
    axes_optical : (K, 3) float64
        Unit emission axes, optical frame.
    powers : (K,) float64
        Relative radiant intensity on the axis.
    exponents : (K,) float64
        Lobe exponents m (cos^m).
    reference_distance_m : float
        Distance d_ref at which a power-1 LED gives irradiance 1 on its axis.
    disc_radius_m : float
        Radius of the emitting disc seen in a mirror.
    rim_fraction : float
        Width of the disc's soft rim as a fraction of its radius.
    """

    positions_optical: np.ndarray
    axes_optical: np.ndarray
    powers: np.ndarray
    exponents: np.ndarray
    reference_distance_m: float
    disc_radius_m: float
    rim_fraction: float = 0.15

    def __post_init__(self) -> None:
        axes = np.asarray(self.axes_optical, dtype=np.float64)
        axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
        object.__setattr__(self, "positions_optical", _readonly(self.positions_optical))
        object.__setattr__(self, "axes_optical", _readonly(axes))
        object.__setattr__(self, "powers", _readonly(self.powers))
        object.__setattr__(self, "exponents", _readonly(self.exponents))

    @property
    def count(self) -> int:
        """Number of LEDs K."""
        return int(self.positions_optical.shape[0])

    def directions_optical(self, points_optical: np.ndarray, k: int) -> np.ndarray:
        """Unit vectors (..., 3) from ``points_optical`` (..., 3) towards LED ``k`` (optical)."""
        d = self.positions_optical[k] - np.asarray(points_optical, dtype=np.float64)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def irradiance(self, points_optical: np.ndarray, k: int) -> np.ndarray:
        """Lighting field E_k (...) at ``points_optical`` (..., 3): inverse square times lobe."""
        d = np.asarray(points_optical, dtype=np.float64) - self.positions_optical[k]
        dist2 = np.einsum("...i,...i->...", d, d)
        cos_t = np.einsum("...i,i->...", d, self.axes_optical[k]) / np.sqrt(dist2)
        lobe = np.maximum(cos_t, 0.0) ** self.exponents[k]
        return self.powers[k] * self.reference_distance_m**2 / dist2 * lobe

    def disc_radiance(
        self, origins_optical: np.ndarray, directions_optical: np.ndarray, k: int
    ) -> np.ndarray:
        """Radiance (...) of LED ``k``'s disc seen along rays; 0 where a ray misses it.

        Parameters
        ----------
        origins_optical : (..., 3) float64
            Ray origins, metres.
        directions_optical : (..., 3) float64
            Unit ray directions.
        """
        o = np.asarray(origins_optical, dtype=np.float64)
        r = np.asarray(directions_optical, dtype=np.float64)
        axis = self.axes_optical[k]
        centre = self.positions_optical[k]
        facing = -np.einsum("...i,i->...", r, axis)  # cos of the angle off the emission axis
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("...i,i->...", centre - o, axis) / np.einsum("...i,i->...", r, axis)
        hit = (facing > 0.0) & (s > 0.0)
        q = o + np.where(hit, s, 0.0)[..., None] * r
        radial = np.linalg.norm(q - centre, axis=-1)
        rim = self.rim_fraction * self.disc_radius_m
        profile = 0.5 * (1.0 - np.tanh((radial - self.disc_radius_m) / rim))
        lobe = np.maximum(facing, 0.0) ** (self.exponents[k] - 1.0)
        peak = self.powers[k] * (self.reference_distance_m / self.disc_radius_m) ** 2
        return np.where(hit, peak * lobe * profile, 0.0)
