"""Forward model of the simplified Hanrahan–Krueger (HK) skin reflectance (paper Eq. 1-5).

Intensity of a surface point under one distant light (NOTES §1, paper Eq. 4 with its typos
mended, see NOTES §5)::

    I = A * p(c, g) * c_i / (c_i + c_r) * (1 - exp(-tau_d * (1/c_i + 1/c_r)))  +  rho * c_i

with c_i = l.n, c_r = v.n (v towards the camera), tau_d = (sigma_s + sigma_a) * d the optical
depth of the epidermis (Eq. 2), A the global scale (sigma_s/sigma_t) * T12 * T21 * L_i, which
is fitted to the images rather than taken as a constant, and p the Henyey–Greenstein phase
function (Eq. 1, standard form: a single 1/(4 pi) and exponent 3/2). The second term is the
Lambertian lobe for multiple scattering (Eq. 3).

Phase convention (:class:`PhaseConvention`): the cosine c of the scattering angle is taken
between the light's propagation direction (-l, into the skin) and the exit direction v, so
c = -l.v (``PhaseConvention.PHYSICAL``, the default). The paper's Eq. 5 writes cos phi = l.v
(``PhaseConvention.PAPER``); with g = 0.81 the two differ by a factor of about 865 between
back- and forward-scattering, so the choice is kept switchable for comparison.

Refraction at the skin surface (part of the original HK model) is not modelled, as in the
paper. The inverse problem (fitting n, rho and A to images) is not in this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from fingerps_recon.errors import FingerpsReconError


class PhaseConvention(Enum):
    """How the cosine of the scattering angle is formed from the light l and view v.

    ``PHYSICAL``: c = -l.v, the angle between the light's propagation direction into the
    skin and the exit direction (back-scattering when the light is next to the camera).
    ``PAPER``: c = l.v, as the paper's Eq. 5 writes it.
    """

    PHYSICAL = "physical"
    PAPER = "paper"


@dataclass(frozen=True)
class SkinParams:
    """Per-material constants of the simplified HK model (paper Sec. 2, NOTES §1).

    Attributes
    ----------
    d_mm : float
        Thickness of the epidermis layer, mm, > 0.
    sigma_s_per_mm : float
        Scattering cross-section, mm^-1, > 0.
    sigma_a_per_mm : float
        Absorption cross-section, mm^-1, >= 0.
    g : float
        Henyey–Greenstein mean cosine (anisotropy), |g| < 1.
    phase : PhaseConvention
        Sign convention of the scattering-angle cosine; a string ("physical" / "paper") is
        accepted and converted.
    """

    d_mm: float = 0.12
    sigma_s_per_mm: float = 30.0
    sigma_a_per_mm: float = 4.5
    g: float = 0.81
    phase: PhaseConvention = PhaseConvention.PHYSICAL

    def __post_init__(self) -> None:
        if isinstance(self.phase, str):
            try:
                object.__setattr__(self, "phase", PhaseConvention(self.phase))
            except ValueError:
                raise FingerpsReconError(
                    f"phase must be one of {[p.value for p in PhaseConvention]}, got {self.phase!r}"
                ) from None
        if not isinstance(self.phase, PhaseConvention):
            raise FingerpsReconError(
                f"phase must be a PhaseConvention, got {type(self.phase).__name__}"
            )
        for name in ("d_mm", "sigma_s_per_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise FingerpsReconError(f"SkinParams.{name} must be finite and > 0, got {value}")
        if not (math.isfinite(self.sigma_a_per_mm) and self.sigma_a_per_mm >= 0):
            raise FingerpsReconError(
                f"SkinParams.sigma_a_per_mm must be finite and >= 0, got {self.sigma_a_per_mm}"
            )
        if not (math.isfinite(self.g) and abs(self.g) < 1):
            raise FingerpsReconError(
                f"SkinParams.g must satisfy |g| < 1 (Henyey–Greenstein), got {self.g}"
            )

    @property
    def sigma_t_per_mm(self) -> float:
        """Total cross-section sigma_s + sigma_a, mm^-1 (Eq. 2)."""
        return self.sigma_s_per_mm + self.sigma_a_per_mm

    @property
    def optical_depth(self) -> float:
        """Optical depth tau_d = sigma_t * d of the layer, dimensionless (Eq. 2)."""
        return self.sigma_t_per_mm * self.d_mm

    @property
    def scattering_albedo(self) -> float:
        """Single-scattering albedo sigma_s / sigma_t, dimensionless (Eq. 2)."""
        return self.sigma_s_per_mm / self.sigma_t_per_mm


#: Fingers and palm, the paper's values (the defaults of :class:`SkinParams`).
FINGER = SkinParams()
#: The paper's plasticine toy.
PLASTICINE = SkinParams(d_mm=0.085, sigma_s_per_mm=50.0, sigma_a_per_mm=3.8, g=0.79)


def henyey_greenstein(cos_theta: np.ndarray | float, g: float) -> np.ndarray:
    """Henyey–Greenstein phase function, sr^-1 (paper Eq. 1, typos mended per NOTES §5).

    p(c, g) = (1 / 4 pi) * (1 - g^2) / (1 + g^2 - 2 g c)^(3/2), normalised so that its
    integral over the sphere of directions is 1.

    Parameters
    ----------
    cos_theta : (...) float
        Cosine of the scattering angle, in [-1, 1].
    g : float
        Mean cosine, |g| < 1.

    Returns
    -------
    p : (...) float
        Same shape as ``cos_theta``; float32 stays float32, anything else gives float64.
    """
    if not (math.isfinite(g) and abs(g) < 1):
        raise FingerpsReconError(f"g must satisfy |g| < 1 (Henyey–Greenstein), got {g}")
    c = np.asarray(cos_theta)
    dtype = c.dtype if c.dtype in (np.float32, np.float64) else np.float64
    c = c.astype(dtype, copy=False)
    g_ = dtype.type(g)
    denom = 1 + g_ * g_ - 2 * g_ * c  # > 0 for |g| < 1 and |c| <= 1
    return (1 - g_ * g_) / (dtype.type(4 * math.pi) * denom * np.sqrt(denom))


def hk_reflectance(
    normals: np.ndarray,
    lights: np.ndarray,
    views: np.ndarray,
    *,
    rho: np.ndarray | float,
    scale: float,
    params: SkinParams = FINGER,
) -> np.ndarray:
    """Pixel intensity under the simplified HK model (paper Eq. 4 with Eq. 1, 3, 5).

    Parameters
    ----------
    normals : (..., 3) float
        Unit surface normals n, PS frame.
    lights : (..., 3) float
        Unit directions l from the surface towards the light, PS frame.
    views : (..., 3) float
        Unit directions v from the surface towards the camera, PS frame; (0, 0, 1) for an
        orthographic camera. ``normals``, ``lights`` and ``views`` broadcast together, e.g.
        normals (H, W, 3) with lights (K, 1, 1, 3) gives (K, H, W).
    rho : (...) float or float
        Lambertian albedo of the multiple-scattering term; broadcasts with the result.
    scale : float
        The global scale A = (sigma_s / sigma_t) * T12 * T21 * L_i of the single-scattering
        term (an unknown fitted to the images, NOTES §1).
    params : SkinParams
        Layer constants and phase convention (:class:`PhaseConvention`, physical by default).

    Returns
    -------
    intensity : (...) float
        A p(c, g) c_i / (c_i + c_r) (1 - exp(-tau_d (1/c_i + 1/c_r))) + rho c_i, and 0 where
        c_i <= 0 (attached shadow) or c_r <= 0 (surface facing away from the camera).
        float32 if all array inputs (rho included) are float32, else float64.
    """
    n = np.asarray(normals)
    lgt = np.asarray(lights)
    v = np.asarray(views)
    for name, arr in (("normals", n), ("lights", lgt), ("views", v)):
        if arr.ndim < 1 or arr.shape[-1] != 3:
            raise FingerpsReconError(f"{name} must have shape (..., 3), got {arr.shape}")
    try:
        np.broadcast_shapes(n.shape, lgt.shape, v.shape)
    except ValueError:
        raise FingerpsReconError(
            f"normals {n.shape}, lights {lgt.shape} and views {v.shape} do not broadcast "
            "together; add singleton axes, e.g. lights[:, None, None, :]"
        ) from None
    if not math.isfinite(scale):
        raise FingerpsReconError(f"scale must be a finite number, got {scale}")
    rho_in = rho if isinstance(rho, (int, float)) else np.asarray(rho)
    dtype = np.result_type(n, lgt, v, rho_in, np.float32)
    n, lgt, v = (a.astype(dtype, copy=False) for a in (n, lgt, v))

    c_i = np.einsum("...k,...k->...", n, lgt)
    c_r = np.einsum("...k,...k->...", n, v)
    c_phi = np.einsum("...k,...k->...", lgt, v)  # Eq. 5
    c_scatter = -c_phi if params.phase is PhaseConvention.PHYSICAL else c_phi
    c_scatter = np.clip(c_scatter, -1, 1)

    lit = (c_i > 0) & (c_r > 0)
    ci = np.where(lit, c_i, 1).astype(dtype, copy=False)
    cr = np.where(lit, c_r, 1).astype(dtype, copy=False)
    tau = dtype.type(params.optical_depth)
    # 1 - exp(-x) via expm1 keeps precision for thin layers.
    attenuation = -np.expm1(-tau * (1 / ci + 1 / cr))
    single = henyey_greenstein(c_scatter, params.g) * (ci / (ci + cr)) * attenuation
    rho_arr = np.asarray(rho_in, dtype=dtype)
    intensity = dtype.type(scale) * single + rho_arr * ci
    return np.where(lit, intensity, 0).astype(dtype, copy=False)
