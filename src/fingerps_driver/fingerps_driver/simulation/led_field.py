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

``LedLayout`` is the rig's LEDs as configured (ring angles, radii, heights, lobes, aims);
``LedLayout.ring`` places them about the scene's apex as a ``LedRing``.
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


@dataclass(frozen=True)
class LedLayout:
    """Where the rig's LEDs sit and how they emit, one entry per LED in index order.

    The defaults are the standard rig: seven LEDs on a ring of ~40 mm radius in the lens
    plane, a little irregular in angle, radius, height, power and lobe, as built.

    Attributes
    ----------
    angles_deg : tuple of float
        Azimuth on the ring in the optical x-y plane, from +x towards +y (clockwise as the
        image is displayed).
    ring_radii_m : tuple of float
        Distance from the optical axis.
    heights_m : tuple of float
        z of each LED (the lens plane is z = 0).
    powers : tuple of float
        Relative on-axis intensity.
    exponents : tuple of float
        m of the cos^m emission lobe.
    aim_offsets_m : tuple of (float, float)
        (x, y) offset from the apex of the point each LED's axis passes through (so the
        lobes are a little off the scene centre).
    disc_radius_m : float
        Radius of each LED's emitting disc as seen in the mirror sphere.
    """

    angles_deg: tuple[float, ...] = (8.0, 57.0, 110.0, 160.0, 209.0, 262.0, 313.0)
    ring_radii_m: tuple[float, ...] = (
        40.0e-3, 38.5e-3, 41.5e-3, 39.0e-3, 42.0e-3, 37.5e-3, 40.5e-3,
    )
    heights_m: tuple[float, ...] = (1.0e-3, -1.5e-3, 0.5e-3, 2.0e-3, -0.5e-3, 1.5e-3, -2.0e-3)
    powers: tuple[float, ...] = (1.00, 0.93, 1.06, 0.88, 0.97, 1.04, 0.91)
    exponents: tuple[float, ...] = (4.5, 5.0, 3.8, 5.5, 4.2, 4.8, 3.5)
    aim_offsets_m: tuple[tuple[float, float], ...] = (
        (3.0e-3, -2.0e-3), (-2.5e-3, 3.0e-3), (4.0e-3, 1.0e-3), (-3.0e-3, -3.5e-3),
        (1.5e-3, 4.0e-3), (-4.0e-3, 0.5e-3), (2.5e-3, -3.0e-3),
    )
    disc_radius_m: float = 1.5e-3

    def ring(self, apex_optical_m: tuple[float, float, float]) -> LedRing:
        """The LEDs aimed about ``apex_optical_m`` (metres, optical frame), whose depth is
        the reference distance of their irradiance."""
        angles = np.deg2rad(np.asarray(self.angles_deg, dtype=np.float64))
        radii = np.asarray(self.ring_radii_m, dtype=np.float64)
        positions = np.stack(
            [radii * np.cos(angles), radii * np.sin(angles), np.asarray(self.heights_m)],
            axis=-1,
        )
        apex = np.asarray(apex_optical_m, dtype=np.float64)
        offsets = np.asarray(self.aim_offsets_m, dtype=np.float64)
        aims = apex + np.concatenate([offsets, np.zeros((len(offsets), 1))], axis=-1)
        return LedRing(
            positions_optical=positions,
            axes_optical=aims - positions,
            powers=np.asarray(self.powers),
            exponents=np.asarray(self.exponents),
            reference_distance_m=float(apex_optical_m[2]),
            disc_radius_m=self.disc_radius_m,
        )
