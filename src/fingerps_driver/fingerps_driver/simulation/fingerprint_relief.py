"""A synthetic fingerprint as a smooth function on the skin: the ridge relief of a finger.

``RidgeRelief`` samples a ``FingerprintPattern`` (``fingerprint_pattern``) at skin
coordinates, with a cubic B-spline interpolant (Unser, "Splines: a perfect fit for signal
and image processing", IEEE SPM 1999: the coefficients by ``scipy.ndimage.spline_filter``
once, then ``map_coordinates(order=3, prefilter=False)``): C2, so surface normals from
finite differences of the relief are smooth, not faceted as with a bilinear interpolant.
Outside the pattern's grid the value fades to 0 over ``fade_mm`` (a C1 smoothstep).

Skin coordinates (``fingertip.FingertipShape.skin_coordinates``, metres from the apex, x
around the finger towards the image's -x, so the camera sees the print mirrored, y along it
towards the shaft) map to the pattern's rolled plane (mm, x
right, y down, origin the grid's top-left corner) by ``rolled = apex_mm + 1000 * skin``:
the apex sits at ``apex_mm``, by default on the grid's centre column 1.5 mm above its
centre, near where ``fingerprint_orientation.draw_model`` puts the cores.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from fingerps_driver.simulation.fingerprint_pattern import FingerprintPattern, generate_fingerprint

_APEX_ABOVE_CENTRE_MM = 1.5
_FADE_MM = 1.0
_SPLINE_MODE = "mirror"


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class RidgeRelief:
    """Ridge value in [-1, 1] (ridges +1) of one synthetic finger at skin coordinates.

    Parameters
    ----------
    pattern : FingerprintPattern
    apex_mm : (float, float), optional
        Where the fingertip's apex lies in the rolled plane (mm); default the grid's centre
        column, 1.5 mm above its centre.
    fade_mm : float
        Width of the fade to 0 at the grid's edges.

    Attributes
    ----------
    pattern : FingerprintPattern
    apex_mm : (float, float)
    """

    def __init__(
        self,
        pattern: FingerprintPattern,
        *,
        apex_mm: tuple[float, float] | None = None,
        fade_mm: float = _FADE_MM,
    ) -> None:
        self.pattern = pattern
        self.apex_mm = (
            (pattern.width_mm / 2.0, pattern.height_mm / 2.0 - _APEX_ABOVE_CENTRE_MM)
            if apex_mm is None
            else (float(apex_mm[0]), float(apex_mm[1]))
        )
        self.fade_mm = float(fade_mm)
        coefficients = ndimage.spline_filter(
            pattern.ridges.astype(np.float64), order=3, mode=_SPLINE_MODE
        )
        coefficients.setflags(write=False)
        self._coefficients = coefficients

    def rolled_mm(self, skin_x_m: np.ndarray, skin_y_m: np.ndarray) -> tuple[np.ndarray, ...]:
        """Rolled-plane position (x, y) mm of skin coordinates (metres from the apex)."""
        return (
            self.apex_mm[0] + 1e3 * np.asarray(skin_x_m),
            self.apex_mm[1] + 1e3 * np.asarray(skin_y_m),
        )

    def value_at_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Ridge value at rolled-plane positions (mm), shaped like ``x_mm``; 0 off the grid."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        p = self.pattern.pixel_mm
        rows, cols = self._coefficients.shape
        inside = np.isfinite(x) & np.isfinite(y)
        xs, ys = np.where(inside, x, -1e3), np.where(inside, y, -1e3)
        window = (
            _smoothstep(xs / self.fade_mm) * _smoothstep((cols * p - xs) / self.fade_mm)
            * _smoothstep(ys / self.fade_mm) * _smoothstep((rows * p - ys) / self.fade_mm)
        )
        out = np.zeros(x.shape)
        near = window > 0.0
        if np.any(near):
            coords = np.stack([ys[near] / p - 0.5, xs[near] / p - 0.5])
            out[near] = window[near] * ndimage.map_coordinates(
                self._coefficients, coords, order=3, prefilter=False, mode=_SPLINE_MODE
            )
        return out

    def __call__(self, skin_x_m: np.ndarray, skin_y_m: np.ndarray) -> np.ndarray:
        """Ridge value at skin coordinates (metres from the apex), shaped like ``skin_x_m``."""
        return self.value_at_mm(*self.rolled_mm(skin_x_m, skin_y_m))


@functools.lru_cache(maxsize=8)
def fingerprint_for_identity(identity: int) -> FingerprintPattern:
    """``generate_fingerprint(identity)``, cached (~1 s each); its arrays are read-only."""
    pattern = generate_fingerprint(int(identity))
    for array in (pattern.ridges, pattern.orientation_rad, pattern.period_mm, pattern.mask):
        array.setflags(write=False)
    return pattern


@functools.lru_cache(maxsize=8)
def relief_for_identity(identity: int) -> RidgeRelief:
    """The ``RidgeRelief`` of ``fingerprint_for_identity(identity)``, cached."""
    return RidgeRelief(fingerprint_for_identity(identity))
