"""The synthetic fingerprint on the simulated fingertip: relief, pose, ground-truth mapping."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pytest
from scipy import ndimage

from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import FingertipShape, PinholeCamera, RigConfig, SimulatedRig
from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical

IDENTITY = 3

# The reference normals: five-point central differences of _spiral_height over 0.5 um
# (truncation and round-off both ~2e-9 rad: halving the step changes them by that much).
_REFERENCE_STEP_M = 0.5e-6
# Points nearer than this to a crease of the surface are left out: both stencils span less.
_SEAM_M = 3e-6
# The rig's normals are central differences over +-0.25 um (``fingertip``), exact to
# O(step^2): 1.6e-5 rad at the most where the ridges are steepest in the image (it shrinks
# fourfold with half the step), elsewhere far less. A change of the surface is far above
# this bound: 0.01 % more ridge period, finger radius or tip elongation moves some normals by
# more than 1e-3 rad.
_NORMALS_TOLERANCE = 3e-5


def _coarse(**finger) -> RigConfig:
    """The standard field of view at a quarter of the resolution (120 um pixels): cheap."""
    return RigConfig(camera=PinholeCamera(width=165, height=124, fx=750.0, fy=750.0),
                     finger=FingertipShape(**finger))


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig(finger=FingertipShape(identity=IDENTITY)))


@pytest.fixture(scope="module")
def truth(rig):
    return rig.finger_truth()


def _path_on_the_shaft(rig: SimulatedRig, a: np.ndarray, b: np.ndarray) -> float:
    """Length (m) of a short path on the shaft's base surface between the points of it
    behind pixel points a and b (3,): straight in (azimuth about the bent axis, dY)."""
    finger = rig.fingertip
    xa, ya, _ = finger.apex_optical_m
    big_r, big_l = finger.radius_m, finger.length_radius_m
    t = np.linspace(0.0, 1.0, 2001)[:, None]
    ends = np.array([[np.arcsin((p[0] - xa) / big_r), p[1] - ya] for p in (a, b)])
    theta, dy = (ends[0] + t * (ends[1] - ends[0])).T
    path = np.stack([big_r * np.sin(theta), dy,
                     big_r * (1 - np.cos(theta)) + dy**2 / (2 * big_l)], axis=-1)
    return float(np.linalg.norm(np.diff(path, axis=0), axis=-1).sum())


def _spiral_height(finger: FingertipShape, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Z - Za (m) of the unposed finger carrying the whorl, at offsets (dx, dy) from its apex
    inside its silhouette, as ``fingertip``'s module docstring defines the surface.

    Ahead of the apex (dy < 0) an ellipsoid of revolution about the finger's axis, its
    semi-axis e R along it; behind it a cylinder of radius R bent along its length with
    radius L. The whorl's phase lives on the arc lengths from the apex over the cap and
    around the cylinder (U, V), warped by sines of wavelength 9 mm (in V) and 13 mm (in U)
    whose phases are the finger seed's first two uniform draws in [0, 2 pi); a spiral of
    ellipses about the core, faded out over 0.7 periods of it; its relief is displaced along
    the base surface's normal.
    """
    big_r, big_l, e = finger.radius_m, finger.length_radius_m, finger.tip_elongation
    ahead = dy < 0.0
    meridian = np.where(ahead, dy / e, 0.0)  # the cap scaled to a sphere along the finger
    off_axis = np.sqrt(dx**2 + meridian**2)
    below = np.sqrt(big_r**2 - off_axis**2)  # R cos(polar angle)
    gradient_x = dx / below
    gradient_y = np.where(ahead, meridian / (e * below), dy / big_l)
    base = big_r - below + np.where(ahead, 0.0, 0.5 * dy**2 / big_l)
    polar = np.arcsin(off_axis / big_r)  # the angle at the sphere's centre from the apex
    arc_ratio = np.divide(big_r * polar, off_axis, out=np.ones_like(dx), where=off_axis > 0)
    along_u = dx * arc_ratio
    along_v = np.where(ahead, dy * arc_ratio, dy)
    first, second = np.random.default_rng(finger.seed).uniform(0.0, 2.0 * np.pi, size=2)
    warp = finger.warp_amplitude_m
    across = along_u - finger.core_offset_m[0] + warp * np.sin(2 * np.pi * along_v / 9e-3 + first)
    along = along_v - finger.core_offset_m[1] + warp * np.sin(2 * np.pi * along_u / 13e-3 + second)
    q = finger.ridge_ellipticity
    ellipse = np.sqrt(q * across**2 + along**2 / q)
    turns = ellipse / finger.ridge_period_m + np.arctan2(along, across) / (2 * np.pi)
    fade = 1.0 - np.exp(-((ellipse / (0.7 * finger.ridge_period_m)) ** 2))
    relief = 0.5 * finger.ridge_height_m * np.cos(2 * np.pi * turns) * fade
    return base - relief * np.sqrt(1.0 + gradient_x**2 + gradient_y**2)


def _fourth_order_slopes(height: Callable[[np.ndarray, np.ndarray], np.ndarray],
                         dx: np.ndarray, dy: np.ndarray,
                         step: float) -> tuple[np.ndarray, np.ndarray]:
    """dh/dx and dh/dy by the five-point central difference (error O(step^4))."""
    def slope(shift_x: float, shift_y: float) -> np.ndarray:
        near = height(dx + shift_x, dy + shift_y) - height(dx - shift_x, dy - shift_y)
        far = height(dx + 2 * shift_x, dy + 2 * shift_y) - height(dx - 2 * shift_x,
                                                                   dy - 2 * shift_y)
        return (8.0 * near - far) / (12.0 * step)
    return slope(step, 0.0), slope(0.0, step)


def test_the_spiral_finger_has_the_normals_of_its_height_field() -> None:
    """The rendered spiral finger's points lie on their pixels' rays and on the surface
    written out in ``_spiral_height``, and carry that surface's normals."""
    rig = SimulatedRig(RigConfig())
    finger = rig.fingertip
    assert finger.spiral and finger.identity is None and finger.roll_deg == 0.0
    xa, ya, za = finger.apex_optical_m
    truth = rig.finger_truth()
    mask = truth.mask
    assert 0.2 < mask.mean() < 0.8
    assert np.all(truth.normals_ps[~mask] == 0.0)  # off the finger: zeros
    points = rig.finger_points_optical()[mask]
    np.testing.assert_allclose(points / points[:, 2:], rig.camera.pixel_rays()[mask], rtol=0,
                               atol=1e-12)
    dx, dy = points[:, 0] - xa, points[:, 1] - ya
    height = functools.partial(_spiral_height, finger)
    np.testing.assert_allclose(za + height(dx, dy), points[:, 2], rtol=0, atol=1e-9)
    # the surface is smooth away from the cap's seam with the shaft (the whorl's V bends
    # there) and from the silhouette (the cone continuation starts there)
    rim = finger.radius_m * np.sin(np.deg2rad(finger.max_slope_deg))
    off_axis = np.hypot(dx, np.where(dy < 0.0, dy / finger.tip_elongation, 0.0))
    smooth = (np.abs(dy) > _SEAM_M) & (off_axis < rim - _SEAM_M)
    assert smooth.mean() > 0.99
    gx, gy = _fourth_order_slopes(height, dx[smooth], dy[smooth], _REFERENCE_STEP_M)
    normals = np.stack([gx, gy, -np.ones_like(gx)], axis=-1)
    normals = optical_to_ps(normals / np.linalg.norm(normals, axis=-1, keepdims=True))
    error = np.linalg.norm(truth.normals_ps[mask][smooth] - normals, axis=-1)
    print(f"\nnormals: largest error {error.max():.2e} rad at {smooth.sum()} points")
    assert error.max() < _NORMALS_TOLERANCE, error.max()
    assert rig.fingerprint is None and truth.rolled_mm is None
    with pytest.raises(FingerpsDriverError, match=r"finger\.identity"):
        rig.rolled_print()


def test_the_relief_is_the_fingerprint(rig, truth):
    """Where the band-passed true depth has a ridge (nearer the camera), the pattern has +1."""
    mask = truth.mask
    depth = np.where(mask, truth.depth_m.astype(np.float64), 0.0)

    def smooth(sigma: float) -> np.ndarray:
        weight = ndimage.gaussian_filter(mask.astype(np.float64), sigma)
        return ndimage.gaussian_filter(depth, sigma) / np.maximum(weight, 1e-9)

    ridge_signal = smooth(5.0) - smooth(1.0)  # > 0 where the skin is raised towards the camera
    x, y = truth.rolled_mm[..., 0], truth.rolled_mm[..., 1]
    pattern = np.zeros(mask.shape)
    pattern[mask] = rig.fingertip.relief.value_at_mm(x[mask], y[mask])
    core = ndimage.binary_erosion(mask, iterations=25) & (truth.normals_ps[..., 2] > 0.7)
    sure = core & (np.abs(pattern) > 0.5)
    assert sure.sum() > 20000
    agree = np.mean(np.sign(ridge_signal[sure]) == np.sign(pattern[sure]))
    assert agree > 0.9, agree


def test_the_rolled_print_and_its_minutiae_are_exposed(rig, truth):
    assert rig.fingerprint is not None and rig.fingerprint.seed == IDENTITY
    card = rig.rolled_print()
    assert card.dtype == np.uint8 and card.shape == rig.fingerprint.ridges.shape
    assert card[~rig.fingerprint.mask].min() == 255
    assert len(rig.fingerprint.minutiae) > 10 and rig.fingerprint.singular_points
    rolled = truth.rolled_mm
    assert rolled.shape == (*truth.mask.shape, 2) and rolled.dtype == np.float32
    assert np.isnan(rolled[~truth.mask]).all() and np.isfinite(rolled[truth.mask]).all()
    # the apex lies where the relief puts it in the rolled plane
    apex = rig.rolled_position_mm(np.asarray(rig.config.finger.apex_optical_m))
    np.testing.assert_allclose(apex, rig.fingertip.relief.apex_mm, atol=1e-9)
    # the finger covers most of the print (and stays inside the grid at this pose)
    inside = rolled[truth.mask]
    assert inside.min() >= 0.0 and inside[:, 0].max() <= rig.fingerprint.width_mm


def test_the_camera_sees_the_print_mirrored(rig, truth):
    """A rolled print is the skin's mirror image: along an image row through the apex the
    rolled x falls as the image x rises (finger pointing up the image), and the rolled y
    rises down the image's centre column, unmirrored."""
    rolled = truth.rolled_mm.astype(np.float64)
    apex = rig.camera.project(np.asarray(rig.config.finger.apex_optical_m)[None])[0]
    row, col = round(float(apex[1])), round(float(apex[0]))
    cols = np.flatnonzero(truth.mask[row])
    rows = np.flatnonzero(truth.mask[:, col])
    # smooth rolled coordinates: the ridges move the hits by < 0.05 mm
    assert np.all(np.diff(rolled[row, cols, 0]) < 0.0)
    assert np.all(np.diff(rolled[rows, col, 1]) > 0.0)


def test_points_5_mm_apart_in_the_rolled_plane_are_5_mm_apart_on_the_skin(rig, truth):
    """Pairs of shaft pixels in one image row ~5 mm apart in the rolled plane: their 3D
    distance along the (bent) shaft surface is the same within 1 % (the bent shaft is not
    developable: its coordinate lines meet at up to ~10 deg from square at the margins)."""
    points = rig.finger_points_optical()
    dy = points[..., 1] - rig.config.finger.apex_optical_m[1]
    shaft = truth.mask & (dy > 1.0e-3)
    rolled = truth.rolled_mm.astype(np.float64)
    errors = []
    for row in np.flatnonzero(shaft.any(axis=1))[::10]:
        cols = np.flatnonzero(shaft[row])
        cols = cols[::-1]
        x = rolled[row, cols, 0]  # falls along the row (mirrored), grows along cols
        for i in range(0, len(cols), 20):
            j = np.searchsorted(x, x[i] + 5.0)
            if j < len(cols):
                in_plane = np.linalg.norm(rolled[row, cols[j]] - rolled[row, cols[i]])
                on_skin = 1e3 * _path_on_the_shaft(rig, points[row, cols[i]],
                                                   points[row, cols[j]])
                errors.append(in_plane / on_skin - 1.0)
    assert len(errors) > 20
    assert np.max(np.abs(errors)) < 0.01, np.max(np.abs(errors))
    print(f"\n{len(errors)} pairs, largest relative error {np.max(np.abs(errors)):.4f}")


def test_meridian_arc_lengths_on_the_cap_are_exact():
    """Skin y along the cap's centre line is the arc length of the ellipsoid's meridian."""
    shape = SimulatedRig(_coarse(identity=IDENTITY)).fingertip
    big_r, e = shape.radius_m, shape.tip_elongation
    beta = np.linspace(0.0, np.deg2rad(65.0), 20001)
    dy, z = -e * big_r * np.sin(beta), big_r * (1 - np.cos(beta))
    polyline = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(dy), np.diff(z)))])
    _, skin_y = shape.skin_coordinates(np.zeros_like(dy), dy)
    np.testing.assert_allclose(-skin_y, polyline, atol=1e-9)


def test_roll_shifts_the_rolled_coordinates_by_r_times_the_angle():
    still = SimulatedRig(_coarse(identity=IDENTITY))
    rolled = SimulatedRig(_coarse(identity=IDENTITY, roll_deg=10.0))
    a, b = still.finger_truth(), rolled.finger_truth()
    assert np.mean(a.mask != b.mask) < 1e-3  # the shape is symmetric about its axis
    points = still.finger_points_optical()[a.mask]
    shift = rolled.rolled_position_mm(points) - still.rolled_position_mm(points)
    expected = 1e3 * still.config.finger.radius_m * np.deg2rad(10.0)  # rolled x is mirrored
    shaft = points[:, 1] > still.config.finger.apex_optical_m[1]
    np.testing.assert_allclose(shift[shaft, 0], expected, atol=1e-9)
    np.testing.assert_allclose(shift[:, 1], 0.0, atol=1e-9)
    # on the cap the shift is rho(dY) * angle, rho the cross-section's radius: smaller
    assert np.all((shift[~shaft, 0] <= expected) & (shift[~shaft, 0] > 0.0))
    # the truth says the same pixel by pixel, within the ridges' lateral effect on the hits
    both = a.mask & b.mask
    pixel_shaft = both & (still.finger_points_optical()[..., 1]
                          > still.config.finger.apex_optical_m[1] + 0.5e-3)
    np.testing.assert_allclose(
        b.rolled_mm[pixel_shaft, 0] - a.rolled_mm[pixel_shaft, 0], expected, atol=0.05)
    assert not np.array_equal(a.normals_ps[both], b.normals_ps[both])


def test_yaw_turns_the_finger_about_the_optical_axis():
    still = SimulatedRig(_coarse(identity=IDENTITY))
    turned = SimulatedRig(_coarse(identity=IDENTITY, yaw_deg=20.0))
    a = still.finger_truth()
    points = still.finger_points_optical()[a.mask]
    xa, ya, za = still.config.finger.apex_optical_m
    c, s = np.cos(np.deg2rad(20.0)), np.sin(np.deg2rad(20.0))
    dx, dy = points[:, 0] - xa, points[:, 1] - ya
    moved = np.stack([xa + c * dx - s * dy, ya + s * dx + c * dy, points[:, 2]], axis=-1)
    height = turned.fingertip.height(moved[:, 0] - xa, moved[:, 1] - ya)[0]
    np.testing.assert_allclose(za + height, points[:, 2], atol=1e-9)
    np.testing.assert_allclose(
        turned.rolled_position_mm(moved), still.rolled_position_mm(points), atol=1e-9)
    assert turned.finger_truth().mask.sum() > 0.8 * a.mask.sum()


@pytest.mark.parametrize("pitch", [-10.0, 12.0])
def test_pitch_turns_the_finger_about_the_optical_x_axis(pitch):
    """A pitched finger's hits, turned back about the apex, lie on the level finger's height
    field, with its normals there, on their pixels' rays; the rolled mapping goes along."""
    level = SimulatedRig(_coarse(identity=IDENTITY))
    pitched = SimulatedRig(_coarse(identity=IDENTITY, pitch_deg=pitch))
    truth = pitched.finger_truth()
    mask = truth.mask
    assert mask.sum() > 0.8 * level.finger_truth().mask.sum()
    points = pitched.finger_points_optical()[mask]
    rays = pitched.camera.pixel_rays()[mask]
    np.testing.assert_allclose(points / points[:, 2:], rays, atol=1e-12)
    shape = level.fingertip
    xa, ya, za = shape.apex_optical_m
    back = pitched.fingertip.to_finger_frame(points)
    dx, dy = back[:, 0] - xa, back[:, 1] - ya
    np.testing.assert_allclose(za + shape.height(dx, dy)[0], back[:, 2], atol=1e-9)
    eps = 0.25e-6
    hx = (shape.height(dx + eps, dy)[0] - shape.height(dx - eps, dy)[0]) / (2 * eps)
    hy = (shape.height(dx, dy + eps)[0] - shape.height(dx, dy - eps)[0]) / (2 * eps)
    expected = np.stack([hx, hy, -np.ones_like(hx)], axis=-1)
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    normals = ps_to_optical(truth.normals_ps[mask].astype(np.float64))
    turned_back = normals @ pitched.fingertip.pitch_matrix()
    np.testing.assert_allclose(turned_back, expected, atol=1e-6)
    np.testing.assert_allclose(
        truth.rolled_mm[mask], level.rolled_position_mm(back), atol=1e-4)
    # + brings the tip (rolled y small) nearer the camera
    tip = truth.rolled_mm[mask][:, 1] < 4.0
    tilt = points[tip, 2] - back[tip, 2]
    assert np.all(tilt < 0) if pitch > 0 else np.all(tilt > 0)


def test_different_identities_are_different_fingers():
    normals = [
        SimulatedRig(_coarse(identity=identity)).finger_truth()
        for identity in (IDENTITY, IDENTITY + 1, None)
    ]
    both = normals[0].mask & normals[1].mask & normals[2].mask
    for i, j in ((0, 1), (0, 2), (1, 2)):
        dots = np.sum(normals[i].normals_ps[both] * normals[j].normals_ps[both], axis=-1)
        assert np.median(np.degrees(np.arccos(np.clip(dots, -1, 1)))) > 2.0
    again = SimulatedRig(_coarse(identity=IDENTITY)).finger_truth()
    np.testing.assert_array_equal(again.normals_ps, normals[0].normals_ps)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("identity", -1),
        ("identity", True),
        ("identity", 2.5),
        ("roll_deg", 46.0),
        ("yaw_deg", -91.0),
        ("pitch_deg", 16.0),
        ("roll_deg", float("nan")),
    ],
)
def test_bad_pose_or_identity_is_refused(field, value):
    with pytest.raises(FingerpsDriverError, match=rf"finger\.{field}"):
        RigConfig(finger=FingertipShape(**{field: value}))
