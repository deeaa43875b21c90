"""burst_motion.estimate_motion: known shifts of textured frames and of the simulated finger."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.scan.burst_motion import estimate_motion


@pytest.mark.parametrize("shape", [(493, 659), (480, 640), (101, 97)])
@pytest.mark.parametrize("shift", [(0.0, 0.0), (3.0, 0.0), (-1.5, 2.25)])
def test_a_shifted_texture_gives_its_shift(shape: tuple[int, int],
                                           shift: tuple[float, float]) -> None:
    rng = np.random.default_rng(1)
    image = scipy.ndimage.gaussian_filter(rng.random(shape), 1.0)  # ridge-like detail
    moved = scipy.ndimage.shift(image, (shift[1], shift[0]), order=3, mode="nearest")
    motion = estimate_motion(image, moved)
    # whole pixels: exact, with no half-pixel bias on odd sizes; half pixels are the worst
    # case of OpenCV's sub-pixel peak (its centroid), ~0.33 px off - far below the 2 px limit
    tolerance = 0.1 if float(shift[0]).is_integer() and float(shift[1]).is_integer() else 0.4
    assert motion.shift_px == pytest.approx(shift, abs=tolerance)
    assert motion.magnitude_px == pytest.approx(np.hypot(*shift), abs=tolerance)
    assert 0.0 < motion.correlation <= 1.0


def test_the_simulated_finger_moved_between_two_frames_of_one_led() -> None:
    rig = SimulatedRig(RigConfig())
    rng = np.random.default_rng(0)
    first = rig.render(Scene.FINGER, [0], rng=rng)
    still = estimate_motion(first, rig.render(Scene.FINGER, [0], rng=rng))
    assert still.magnitude_px < 0.05
    moved = estimate_motion(first, rig.render(Scene.FINGER, [0], rng=rng,
                                              finger_shift_px=(4.0, -1.0)))
    assert moved.shift_px == pytest.approx((4.0, -1.0), abs=0.1)


def test_frames_of_different_sizes_are_refused() -> None:
    with pytest.raises(FingerpsReconError, match="one size"):
        estimate_motion(np.zeros((20, 20)), np.zeros((20, 21)))
