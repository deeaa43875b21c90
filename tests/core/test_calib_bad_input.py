"""Bad input to the calibration cores: each case is refused with a message saying what is
wrong and what to do (fingerps_calib.sphere_calibration, flat_field_calibration).

Images from the simulated rig (fingerps_driver.simulation), altered where the rig has no
knob for the fault.
"""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_calib.sphere_calibration import calibrate_lights
from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig

RADIUS = 4e-3
#: What calib_node asks for: the whole sphere, 63-117 mm away (90 mm +- 30 %).
NODE_CHECKS = {"require_whole_sphere": True, "expected_distance_m": (0.063, 0.117)}


def _render(rig: SimulatedRig, scene: Scene, seed: int = 0) -> np.ndarray:
    return np.stack([rig.render(scene, [k], rng=np.random.default_rng(seed + k))
                     for k in range(rig.led_count)])


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig())


@pytest.fixture(scope="module")
def sphere(rig) -> np.ndarray:
    return _render(rig, Scene.SPHERE)


def _calibrate(rig: SimulatedRig, images: np.ndarray, radius: float = RADIUS):
    return calibrate_lights(images, camera_matrix=rig.camera_matrix, radius_m=radius,
                            **NODE_CHECKS)


def test_the_good_case_passes_the_node_checks(rig, sphere):
    result = _calibrate(rig, sphere)
    assert result.ok, result.problems
    assert np.all(result.highlight_contrast > 10)
    assert np.all(result.saturated_px < 100)  # the sim's highlights saturate ~60 px


def test_no_sphere_in_the_image(rig):
    for images in (_render(rig, Scene.EMPTY), _render(rig, Scene.WHITE_TARGET)):
        result = _calibrate(rig, images)
        assert not result.ok
        (problem,) = result.problems
        assert problem.startswith("sphere not found") and "dark background" in problem


def test_another_object_is_not_taken_for_the_sphere(rig):
    result = _calibrate(rig, _render(rig, Scene.FINGER))
    (problem,) = result.problems  # nothing more is analysed
    assert problem.startswith("the object in view is not the sphere: its silhouette fits")
    assert np.all(np.isnan(result.directions_optical))


def test_sphere_cut_by_the_frame():
    cut = SimulatedRig(RigConfig(sphere_center_optical_m=(-9.0e-3, 0.0, 0.094)))
    result = _calibrate(cut, _render(cut, Scene.SPHERE))
    assert not result.ok
    assert any("cut by the image border (left)" in p and "middle of the view" in p
               for p in result.problems), result.problems
    # Without the requirement the visible outline still gives an accurate fit.
    lenient = calibrate_lights(_render(cut, Scene.SPHERE), camera_matrix=cut.camera_matrix,
                               radius_m=RADIUS)
    assert lenient.ok, lenient.problems


def test_a_missing_highlight_is_named(rig, sphere):
    matte = SimulatedRig(RigConfig(sphere_specular_reflectance=0.0))
    images = sphere.copy()
    images[3] = matte.render(Scene.SPHERE, [3], rng=np.random.default_rng(3))
    result = _calibrate(rig, images)
    assert not result.ok
    assert [p.split(":")[0] for p in result.problems] == ["LED 3"]
    assert "no highlight" in result.problems[0] and "LED 3 lights" in result.problems[0]
    assert np.all(np.isnan(result.directions_optical[3]))
    dark = sphere.copy()
    dark[5] = rig.render(Scene.SPHERE, [], rng=np.random.default_rng(5))  # LED 5 never lit
    result = _calibrate(rig, dark)
    assert [p.split(":")[0] for p in result.problems] == ["LED 5"]
    assert "no highlight" in result.problems[0]


def test_highlights_saturated_into_blobs():
    blurred = SimulatedRig(RigConfig(psf_sigma_px=6.0, exposure_gain=4.0))
    result = _calibrate(blurred, _render(blurred, Scene.SPHERE))
    assert not result.ok
    assert all("saturated into a blob" in p and "lower the exposure" in p
               for p in result.problems), result.problems
    assert np.all(result.saturated_px > 1000)


def test_a_saturated_sphere(rig, sphere):
    hot = SimulatedRig(RigConfig(exposure_gain=40.0))
    result = _calibrate(hot, _render(hot, Scene.SPHERE))
    assert not result.ok
    assert any("whole sphere is saturated" in p for p in result.problems), result.problems


def test_a_wrong_radius_shows_as_a_wrong_distance(rig, sphere):
    # The silhouette is a cone: the edge residual cannot tell the radius; the distance can.
    wrong = _calibrate(rig, sphere, radius=2e-3)
    right = _calibrate(rig, sphere)
    assert wrong.edge_rms_px == pytest.approx(right.edge_rms_px, abs=1e-6)
    assert not wrong.ok
    (problem,) = wrong.problems
    assert "47.1 mm from the camera" in problem and "is the radius right?" in problem
    assert "radius of 3.82 mm" in problem  # what would put the sphere at 90 mm


def test_images_of_the_wrong_kind(rig):
    with pytest.raises(FingerpsCalibError, match=r"\(K, H, W\)"):
        calibrate_lights(np.zeros((10, 10)), camera_matrix=rig.camera_matrix, radius_m=RADIUS)
    with pytest.raises(FingerpsCalibError, match="radius"):
        calibrate_lights(np.zeros((2, 10, 10)), camera_matrix=rig.camera_matrix, radius_m=0)


def test_a_white_target_that_is_not_flat(rig):
    finger = _render(rig, Scene.FINGER)
    with pytest.raises(FingerpsCalibError, match=r"smooth lighting field.*LED 0 .*flat, clean"):
        flat_field_maps(finger)
    white = _render(rig, Scene.WHITE_TARGET, seed=20)
    vv, uu = np.mgrid[0:white.shape[1], 0:white.shape[2]]
    shadow = np.where((uu - 500) ** 2 + (vv - 100) ** 2 < 60**2, 0.3, 1.0)
    with pytest.raises(FingerpsCalibError, match="not flat and uniform"):
        flat_field_maps(np.round(white * shadow).astype(np.uint8))
    good = flat_field_maps(white)
    assert np.all(good.fit_residuals < 0.01)  # 0.5 % on the simulated rig


def test_a_saturated_white_target(rig):
    white = _render(rig, Scene.WHITE_TARGET, seed=30)
    bright = np.clip(white.astype(np.float64) * 1.5, 0, 255).astype(np.uint8)
    with pytest.raises(FingerpsCalibError, match=r"LED 0:.*saturated.*lower the exposure"):
        flat_field_maps(bright)
