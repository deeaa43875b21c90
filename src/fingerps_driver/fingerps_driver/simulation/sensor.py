"""Image sensor: shot noise, read noise, an ambient/dark level, quantisation to 8 or 12 bits.

Signals are given as fractions of full scale (1.0 = ``full_well_e`` electrons = the maximum
digital value). Per pixel the electron count is signal + ambient, with Poisson shot noise
approximated by a Gaussian of variance equal to the count (exact enough above a few
electrons and much faster), plus Gaussian read noise; then rounding and clipping to
0..2**bit_depth - 1. One standard-normal draw per pixel from the caller's generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """Noise and quantisation of the camera.

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
    """

    bit_depth: int
    full_well_e: float
    read_noise_e: float
    ambient_fraction: float

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
            Noiseless signal, fraction of full scale (not modified).
        rng : numpy.random.Generator

        Returns
        -------
        frame : (H, W) uint8 or uint16
        """
        electrons_per_unit = np.float32(self.full_well_e)
        level = signal + np.float32(self.ambient_fraction)
        sigma = np.sqrt(
            level * np.float32(1.0 / electrons_per_unit)
            + np.float32((self.read_noise_e / electrons_per_unit) ** 2)
        )
        noisy = rng.standard_normal(signal.shape, dtype=np.float32)
        noisy *= sigma
        noisy += level
        noisy *= np.float32(self.max_value)
        noisy += np.float32(0.5)
        np.clip(noisy, 0.0, self.max_value, out=noisy)
        return noisy.astype(self.dtype)
