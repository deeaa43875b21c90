"""Image sensor: shot noise, read noise, an ambient/dark level, quantisation to 8 or 12 bits.

Signals are given as fractions of full scale (1.0 = ``full_well_e`` electrons = the maximum
digital value). Per pixel the electron count is signal + ambient, with Poisson shot noise
approximated by a Gaussian of variance equal to the count (exact enough above a few
electrons), plus Gaussian read noise; then rounding and clipping to 0..2**bit_depth - 1.

Speed: the standard-normal deviates are drawn from the caller's generator as uniform 16-bit
integers mapped through a table of the normal quantiles at (i + 1/2) / 65536 (rescaled to
unit variance; tails cut at 4.3 sigma): a table look-up instead of
``Generator.standard_normal``'s transform, and indistinguishable for sensor noise.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from functools import cache

import numpy as np

_TABLE_BITS = 16


@cache
def _normal_quantiles() -> np.ndarray:
    """(65536,) float32 unit-variance table of standard-normal quantiles."""
    normal = statistics.NormalDist()
    size = 1 << _TABLE_BITS
    table = np.array([normal.inv_cdf((i + 0.5) / size) for i in range(size)])
    table /= table.std()
    table = table.astype(np.float32)
    table.setflags(write=False)
    return table


def standard_normal(shape: tuple[int, ...], *, rng: np.random.Generator) -> np.ndarray:
    """Standard-normal deviates (``shape``) float32 drawn from ``rng`` by table look-up."""
    indices = rng.integers(0, 1 << _TABLE_BITS, size=shape, dtype=np.uint16)
    return np.take(_normal_quantiles(), indices)


@dataclass(frozen=True)
class SensorModel:
    """Exposure, noise and quantisation of the camera; the defaults are the rig's sensor.

    Attributes
    ----------
    bit_depth : int
        8 (uint8 output) or 12 (uint16 output holding 0..4095).
    full_well_e : float
        Electrons at full scale.
    read_noise_e : float
        Read noise, electrons rms.
    ambient_fraction : float
        Ambient light plus dark current in every frame, fraction of full scale.
    exposure_gain : float
        Fraction of full scale per unit radiance of the finger and the sphere; the default
        puts the brightest finger pixels under the brightest LED at ~80 % of full scale.
    """

    bit_depth: int = 8
    full_well_e: float = 10000.0
    read_noise_e: float = 10.0
    ambient_fraction: float = 0.002
    exposure_gain: float = 1.3

    @property
    def max_value(self) -> int:
        """Largest digital value: 255 or 4095."""
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type:
        """numpy dtype of the frames."""
        return np.uint8 if self.bit_depth <= 8 else np.uint16

    def expose(self, signal: np.ndarray, *, rng: np.random.Generator) -> np.ndarray:
        """Digitise a noiseless image.

        Parameters
        ----------
        signal : (H, W) float32
            Noiseless signal, fraction of full scale, >= 0 (not modified).
        rng : numpy.random.Generator

        Returns
        -------
        frame : (H, W) uint8 or uint16
        """
        top = float(self.max_value)
        level = signal * np.float32(top)  # digital numbers
        level += np.float32(self.ambient_fraction * top)
        # variance in DN^2: shot (level * top / full_well) + read
        sigma = level * np.float32(top / self.full_well_e)
        sigma += np.float32((self.read_noise_e * top / self.full_well_e) ** 2)
        np.sqrt(sigma, out=sigma)
        sigma *= standard_normal(signal.shape, rng=rng)
        level += sigma
        level += np.float32(0.5)
        np.clip(level, 0.0, top, out=level)
        return level.astype(self.dtype)
