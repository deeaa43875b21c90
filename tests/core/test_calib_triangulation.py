"""Tests of fingerps_calib.lights.led_triangulation: LED positions from several sphere placements.

Analytic cases build the placements' rays directly (origins anywhere, directions towards a
known LED); the simulated case calibrates two real placements of the rig's sphere and
compares with the rig's LED positions and with the directions from the finger apex.
"""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.led_triangulation import (
    Placement,
    combine_placements,
    triangulate_leds,
    triangulate_point,
)
from fingerps_calib.lights.sphere_calibration import calibrate_lights
from fingerps_driver import simulation

LEDS = np.array([[0.040, 0.005, 0.001], [-0.020, 0.035, -0.002], [-0.030, -0.028, 0.0015]])


# An angle read as arccos(a . b) near 0 resolves only sqrt(2 delta) rad, delta being how far
# the float64 dot of two unit 3-vectors falls below 1 by rounding alone: normalising each
# (norm, divide) and the 3-term sum leave delta <= ~8 eps, so an exact angle of 0 can read
# as sqrt(16 eps) rad = 3.4e-6 deg (a dot of 1 - eps reads 1.2e-6 deg; measured up to 2.5 eps).
ARCCOS_RESOLUTION_DEG = float(np.degrees(np.sqrt(16 * np.finfo(np.float64).eps)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(_unit(a) * _unit(b), axis=-1), -1, 1)))


def _placement(centre: np.ndarray, *, leds: np.ndarray = LEDS,
               tilt: np.ndarray | None = None) -> Placement:
    """A placement whose rays start on a 4 mm sphere at ``centre`` and point at ``leds``
    (or off them by small rotations ``tilt`` (K, 3), radians about each axis)."""
    towards_camera = _unit(-centre)
    origins = centre + 0.004 * _unit(towards_camera + 0.3 * _unit(leds - centre))
    directions = _unit(leds - origins)
    if tilt is not None:
        directions = _unit(directions + np.cross(tilt, directions))
    n = len(leds)
    return Placement(sphere_center_optical_m=centre, radius_m=0.004, edge_rms_px=0.1,
                     highlight_points_optical_m=origins, directions_optical=directions,
                     highlights_uv=np.zeros((n, 2)), residuals_px=np.full(n, 0.05))


CENTRES = [np.array([0.002, -0.0015, 0.094]), np.array([-0.006, 0.002, 0.092]),
           np.array([0.004, 0.003, 0.1])]


def test_triangulate_point_exact_and_residual():
    target = np.array([0.01, -0.02, 0.005])
    origins = np.array([[0.0, 0.0, 0.09], [0.01, 0.0, 0.1], [-0.01, 0.01, 0.095]])
    point, rms = triangulate_point(origins, target - origins)
    np.testing.assert_allclose(point, target, atol=1e-12)
    assert rms < 1e-12
    # Two rays shifted 1 mm apart, symmetrically, along their common normal: the point is
    # half-way, 0.5 mm from each.
    d = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    p = np.array([[0.0, 0.0, 0.0005], [0.0, 0.0, -0.0005]])
    point, rms = triangulate_point(p, d)
    np.testing.assert_allclose(point, 0.0, atol=1e-12)
    assert rms == pytest.approx(0.0005)
    with pytest.raises(FingerpsCalibError, match="parallel"):
        triangulate_point(p, np.array([[1.0, 0, 0], [2.0, 0, 0]]))
    with pytest.raises(FingerpsCalibError, match=r"N >= 2"):
        triangulate_point(p[:1], d[:1])


def test_exact_rays_give_the_leds_and_the_directions_from_the_reference():
    placements = [_placement(c) for c in CENTRES]
    reference = np.array([0.0, 0.0025, 0.09])
    result = triangulate_leds(placements, reference_point_optical_m=reference)
    assert result.ok, result.problems
    np.testing.assert_allclose(result.led_positions_optical_m, LEDS, atol=1e-9)
    np.testing.assert_allclose(result.directions_optical, _unit(LEDS - reference), atol=1e-9)
    assert np.all(result.position_residuals_m < 1e-9)
    # The rays meet exactly; what is left is the arccos's resolution (the LED's float64
    # position error, ~cond 1e3 x eps x 0.1 m, turns the rays by only ~1e-13 rad).
    assert np.all(result.direction_residuals_deg <= ARCCOS_RESOLUTION_DEG), \
        result.direction_residuals_deg
    assert np.all(result.ray_angles_deg > 3.0)
    np.testing.assert_allclose(result.directions_ps[:, 1:], -result.directions_optical[:, 1:])
    # Default reference: the mean of the sphere centres.
    default = triangulate_leds(placements)
    np.testing.assert_allclose(default.reference_point_optical_m, np.mean(CENTRES, axis=0))


def test_direction_errors_move_the_led_mostly_along_its_rays():
    # 0.1 deg of error in each ray: the LED moves ~mm along the rays, but the direction
    # from a reference point near the placements turns by much less than 0.1 deg.
    rng = np.random.default_rng(0)
    placements = [_placement(c, tilt=rng.normal(0, np.radians(0.1) / np.sqrt(3), (3, 3)))
                  for c in CENTRES]
    reference = np.mean(CENTRES, axis=0)
    result = triangulate_leds(placements, reference_point_optical_m=reference)
    assert result.ok, result.problems
    error_mm = 1e3 * np.linalg.norm(result.led_positions_optical_m - LEDS, axis=1)
    errors_deg = _angle_deg(result.directions_optical, LEDS - reference)
    assert np.all(error_mm < 5.0)
    assert np.all(errors_deg < 0.1), errors_deg
    assert np.all(result.position_residuals_m < 0.5e-3)
    assert np.all(result.range_uncertainty_m > result.position_residuals_m)


def test_checks_name_the_led_and_what_to_do():
    close = triangulate_leds([_placement(CENTRES[0]),
                              _placement(CENTRES[0] + np.array([0.0005, 0.0, 0.0]))])
    assert not close.ok
    assert all("too close" in p and "move the sphere by at least" in p
               for p in close.problems), close.problems
    # One of three placements' rays shifted by 3 mm (the sphere moved during the capture).
    # (Two rays always have a closest point; only a third can contradict them fully.)
    moved = _placement(CENTRES[1])
    moved = Placement(moved.sphere_center_optical_m, moved.radius_m, moved.edge_rms_px,
                      moved.highlight_points_optical_m + np.array([0.003, 0.0, 0.0]),
                      moved.directions_optical, moved.highlights_uv, moved.residuals_px)
    inconsistent = triangulate_leds([_placement(CENTRES[0]), moved, _placement(CENTRES[2])])
    assert not inconsistent.ok
    assert any("miss each other" in p for p in inconsistent.problems)
    # A highlight missing in one of two placements.
    missing = _placement(CENTRES[1])
    directions = missing.directions_optical.copy()
    directions[2] = np.nan
    missing = Placement(missing.sphere_center_optical_m, 0.004, 0.1,
                        missing.highlight_points_optical_m, directions,
                        missing.highlights_uv, missing.residuals_px)
    result = triangulate_leds([_placement(CENTRES[0]), missing])
    assert [p.split(":")[0] for p in result.problems] == ["LED 2"]
    assert np.all(np.isnan(result.led_positions_optical_m[2]))
    assert np.all(np.isfinite(result.led_positions_optical_m[:2]))
    # Rays pointing away from the LEDs meet behind the spheres.
    flipped = [Placement(pl.sphere_center_optical_m, 0.004, 0.1,
                         pl.highlight_points_optical_m, -pl.directions_optical,
                         pl.highlights_uv, pl.residuals_px)
               for pl in (_placement(CENTRES[0]), _placement(CENTRES[1]))]
    assert any("behind" in p for p in triangulate_leds(flipped).problems)


def test_bad_input_raises():
    with pytest.raises(FingerpsCalibError, match="two or more"):
        triangulate_leds([_placement(CENTRES[0])])
    with pytest.raises(FingerpsCalibError, match="different LED counts"):
        triangulate_leds([_placement(CENTRES[0]), _placement(CENTRES[1], leds=LEDS[:2])])
    with pytest.raises(FingerpsCalibError, match="different LED counts"):
        combine_placements([_placement(CENTRES[0]), _placement(CENTRES[1], leds=LEDS[:2])])
    with pytest.raises(FingerpsCalibError, match="no sphere placement"):
        combine_placements([])
    with pytest.raises(FingerpsCalibError, match="reference point"):
        triangulate_leds([_placement(c) for c in CENTRES[:2]],
                         reference_point_optical_m=np.array([0.0, 1.0]))
    with pytest.raises(FingerpsCalibError, match="shape"):
        Placement(np.zeros(2), 0.004, 0.1, np.zeros((3, 3)), np.zeros((3, 3)),
                  np.zeros((3, 2)), np.zeros(3))


def test_combine_one_placement_keeps_its_directions():
    single = _placement(CENTRES[0])
    combined = combine_placements([single])
    assert combined.ok and combined.triangulation is None
    np.testing.assert_array_equal(combined.directions_optical, single.directions_optical)
    assert combined.led_positions_optical_m.shape == (0, 3)
    both = combine_placements([single, _placement(CENTRES[1])])
    assert both.ok and both.triangulation is not None
    np.testing.assert_allclose(both.led_positions_optical_m, LEDS, atol=1e-9)
    np.testing.assert_array_equal(both.sphere_center_optical_m, CENTRES[1])  # the latest


def test_two_simulated_placements_give_the_leds_and_the_apex_directions():
    errors, positions = [], []
    placements = []
    for index, centre in enumerate([(2.0e-3, -1.5e-3, 0.094), (-5.5e-3, 2.0e-3, 0.094)]):
        sphere = simulation.MirrorSphere(center_optical_m=centre)
        rig = simulation.SimulatedRig(simulation.RigConfig(sphere=sphere))
        images = np.stack([
            rig.render(simulation.Scene.SPHERE, [k], rng=np.random.default_rng(10 * index + k))
            for k in range(rig.led_count)])
        result = calibrate_lights(images, camera_matrix=rig.camera_matrix,
                                  radius_m=rig.config.sphere.radius_m)
        assert result.ok, result.problems
        placements.append(Placement.from_result(result))
    apex = np.asarray(rig.config.finger.apex_optical_m)
    combined = combine_placements(placements, reference_point_optical_m=apex)
    assert combined.ok, combined.problems
    errors = _angle_deg(combined.directions_optical, rig.led_positions_optical - apex)
    positions = 1e3 * np.linalg.norm(
        combined.led_positions_optical_m - rig.led_positions_optical, axis=1)
    print(f"\ndirection errors from the apex (deg) {np.round(errors, 3).tolist()}"
          f"\nLED position errors (mm) {np.round(positions, 2).tolist()}")
    assert np.all(errors < 0.2)   # measured 0.01-0.10
    assert np.all(positions < 3.0)  # measured 0.3-1.9, mostly along the rays
    # The single placement's own directions differ from the apex's by degrees: the gain.
    single = _angle_deg(placements[0].directions_optical, rig.led_positions_optical - apex)
    assert single.max() > 1.0
