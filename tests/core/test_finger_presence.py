"""finger_presence.detect_finger on analytic frames and on the simulated rig."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.scan.finger_presence import detect_finger


def test_a_bright_disc_is_found_with_its_box_and_coverage() -> None:
    rows, cols = np.mgrid[0:200, 0:300]
    dark = np.full((200, 300), 10, dtype=np.uint8)
    lit = dark.copy()
    disc = (rows - 80) ** 2 + (cols - 200) ** 2 < 40 ** 2
    lit[disc] = 150
    found = detect_finger(lit, dark=dark, full_scale=255)
    assert found.present
    assert found.coverage == pytest.approx(disc.mean(), rel=0.15)  # the smoothing widens it
    r0, c0, r1, c1 = found.bbox
    assert abs(r0 - 40) <= 3 and abs(r1 - 120) <= 3 and abs(c0 - 160) <= 3 and abs(c1 - 240) <= 3
    assert found.centroid == pytest.approx((80, 200), abs=1.0)
    assert "finger at row 80" in found.describe()


def test_ambient_light_alone_and_small_spots_are_not_a_finger() -> None:
    ambient = np.full((100, 100), 120, dtype=np.uint8)  # the dark frame cancels it
    assert not detect_finger(ambient, dark=ambient, full_scale=255).present
    spot = np.zeros((100, 100), dtype=np.uint8)
    spot[10:14, 10:14] = 255
    found = detect_finger(spot, full_scale=255, min_coverage=0.05)
    assert not found.present and found.coverage < 0.01


def test_the_simulated_finger_is_present_and_the_empty_scene_is_not() -> None:
    rig = SimulatedRig(RigConfig())
    rng = np.random.default_rng(0)
    dark = rig.render(Scene.FINGER, [], rng=rng)
    finger = detect_finger(rig.render(Scene.FINGER, [0], rng=rng), dark=dark, full_scale=255)
    assert finger.present and 0.4 < finger.coverage < 0.7
    empty = detect_finger(rig.render(Scene.EMPTY, [0], rng=rng), dark=dark, full_scale=255)
    assert not empty.present and empty.bbox is None


def test_bad_input_is_refused() -> None:
    with pytest.raises(FingerpsReconError, match="dark frame"):
        detect_finger(np.zeros((10, 10)), dark=np.zeros((5, 5)), full_scale=255)
    with pytest.raises(FingerpsReconError, match=r"\(H, W\)"):
        detect_finger(np.zeros((3, 10, 10)), full_scale=255)
