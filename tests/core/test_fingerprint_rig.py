"""The synthetic fingerprint on the simulated fingertip: relief, pose, ground-truth mapping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import RigConfig, SimulatedRig
from fingerps_driver.simulation.fingertip import trace_fingertip
from fingerps_recon.photometric.frames import ps_to_optical

IDENTITY = 3

# Normals of the default rig (the analytic spiral, no fingerprint, no pose) at these pixels:
# the fingerprint and pose options must leave it as it renders them; (0, 0, 0) is off the
# finger.
_PIXELS = [(300, 330), (60, 330), (200, 140), (200, 520), (470, 300), (330, 250), (120, 400)]
_NORMALS_BEFORE = [
    (0.16310403429679438, 0.16514333406338008, 0.9726894433530884),
    (0.0, 0.0, 0.0),
    (-0.8007457907006233, 0.4132572289716412, 0.43361808239269034),
    (0.7522730327199848, 0.37820061381692555, 0.5394901110778375),
    (-0.15040443112898635, -0.3278765367332411, 0.9326711552077621),
    (-0.24217591855416024, 0.021902777085193063, 0.9699850992816359),
    (0.31029608943402925, 0.6818174784518366, 0.6624509513613278),
]


def _coarse(**kwargs) -> RigConfig:
    """The standard field of view at a quarter of the resolution (120 um pixels): cheap."""
    return RigConfig(width=165, height=124, focal_px=750.0, **kwargs)


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig(finger_identity=IDENTITY))


@pytest.fixture(scope="module")
def truth(rig):
    return rig.finger_truth()


def _path_on_the_shaft(rig: SimulatedRig, a: np.ndarray, b: np.ndarray) -> float:
    """Length (m) of a short path on the shaft's base surface between the points of it
    behind pixel points a and b (3,): straight in (azimuth about the bent axis, dY)."""
    c = rig.config
    xa, ya, _ = c.finger_apex_optical_m
    big_r, big_l = c.finger_radius_m, c.finger_length_radius_m
    t = np.linspace(0.0, 1.0, 2001)[:, None]
    ends = np.array([[np.arcsin((p[0] - xa) / big_r), p[1] - ya] for p in (a, b)])
    theta, dy = (ends[0] + t * (ends[1] - ends[0])).T
    path = np.stack([big_r * np.sin(theta), dy,
                     big_r * (1 - np.cos(theta)) + dy**2 / (2 * big_l)], axis=-1)
    return float(np.linalg.norm(np.diff(path, axis=0), axis=-1).sum())


# How far another machine's float64 arithmetic may move these normals (libm or SIMD sin, cos,
# arcsin, sqrt differ by a few ulps; AVX-512 numpy uses other kernels than AVX2):
# - the normal is a central difference of h over 2 * _FD_STEP_M (0.5 um): an error of one
#   ulp of h's 8 mm-sized terms (1.7e-18 m) moves a gradient component by 3.5e-12 (measured
#   6e-12 with h perturbed by +-1 ulp); allowing 32 ulps through h's ~30 operations: 2e-10;
# - a stop of the secant search flipped by rounding (|f| against 1e-12 m) leaves one step
#   more or less: measured <= 8.6e-11 (tolerance 1e-13 instead);
# so 5e-10 on the unit normal's components (a bound, not an estimate: on an AVX-512 machine,
# AVX-512 off with tools/no_avx512_env.sh moves them by 6.4e-15). A change of the geometry is
# far above it: 1 ppm more finger radius, tip elongation, ridge height or period moves them
# by 1.5e-7 .. 3e-5.
_NORMALS_ATOL = 5e-10


def test_the_spiral_finger_is_unchanged():
    rig = SimulatedRig(RigConfig())
    rays = rig.camera.pixel_rays()
    surface = trace_fingertip(rig.fingertip, np.stack([rays[r, c] for r, c in _PIXELS])[None])
    np.testing.assert_allclose(surface.normals_ps[0], np.array(_NORMALS_BEFORE), rtol=0,
                               atol=_NORMALS_ATOL)
    assert np.all(surface.normals_ps[0][1] == 0.0)  # off the finger: zeros by construction
    assert rig.fingerprint is None and rig.finger_truth().rolled_mm is None
    with pytest.raises(FingerpsDriverError, match="finger_identity"):
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
    apex = rig.rolled_position_mm(np.asarray(rig.config.finger_apex_optical_m))
    np.testing.assert_allclose(apex, rig.fingertip.relief.apex_mm, atol=1e-9)
    # the finger covers most of the print (and stays inside the grid at this pose)
    inside = rolled[truth.mask]
    assert inside.min() >= 0.0 and inside[:, 0].max() <= rig.fingerprint.width_mm


def test_the_camera_sees_the_print_mirrored(rig, truth):
    """A rolled print is the skin's mirror image: along an image row through the apex the
    rolled x falls as the image x rises (finger pointing up the image), and the rolled y
    rises down the image's centre column, unmirrored."""
    rolled = truth.rolled_mm.astype(np.float64)
    apex = rig.camera.project(np.asarray(rig.config.finger_apex_optical_m)[None])[0]
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
    dy = points[..., 1] - rig.config.finger_apex_optical_m[1]
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
    shape = SimulatedRig(_coarse(finger_identity=IDENTITY)).fingertip
    big_r, e = shape.radius_m, shape.tip_elongation
    beta = np.linspace(0.0, np.deg2rad(65.0), 20001)
    dy, z = -e * big_r * np.sin(beta), big_r * (1 - np.cos(beta))
    polyline = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(dy), np.diff(z)))])
    _, skin_y = shape.skin_coordinates(np.zeros_like(dy), dy)
    np.testing.assert_allclose(-skin_y, polyline, atol=1e-9)


def test_roll_shifts_the_rolled_coordinates_by_r_times_the_angle():
    still = SimulatedRig(_coarse(finger_identity=IDENTITY))
    rolled = SimulatedRig(_coarse(finger_identity=IDENTITY, finger_roll_deg=10.0))
    a, b = still.finger_truth(), rolled.finger_truth()
    assert np.mean(a.mask != b.mask) < 1e-3  # the shape is symmetric about its axis
    points = still.finger_points_optical()[a.mask]
    shift = rolled.rolled_position_mm(points) - still.rolled_position_mm(points)
    expected = 1e3 * still.config.finger_radius_m * np.deg2rad(10.0)  # rolled x is mirrored
    shaft = points[:, 1] > still.config.finger_apex_optical_m[1]
    np.testing.assert_allclose(shift[shaft, 0], expected, atol=1e-9)
    np.testing.assert_allclose(shift[:, 1], 0.0, atol=1e-9)
    # on the cap the shift is rho(dY) * angle, rho the cross-section's radius: smaller
    assert np.all((shift[~shaft, 0] <= expected) & (shift[~shaft, 0] > 0.0))
    # the truth says the same pixel by pixel, within the ridges' lateral effect on the hits
    both = a.mask & b.mask
    pixel_shaft = both & (still.finger_points_optical()[..., 1]
                          > still.config.finger_apex_optical_m[1] + 0.5e-3)
    np.testing.assert_allclose(
        b.rolled_mm[pixel_shaft, 0] - a.rolled_mm[pixel_shaft, 0], expected, atol=0.05)
    assert not np.array_equal(a.normals_ps[both], b.normals_ps[both])


def test_yaw_turns_the_finger_about_the_optical_axis():
    still = SimulatedRig(_coarse(finger_identity=IDENTITY))
    turned = SimulatedRig(_coarse(finger_identity=IDENTITY, finger_yaw_deg=20.0))
    a = still.finger_truth()
    points = still.finger_points_optical()[a.mask]
    xa, ya, za = still.config.finger_apex_optical_m
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
    level = SimulatedRig(_coarse(finger_identity=IDENTITY))
    pitched = SimulatedRig(_coarse(finger_identity=IDENTITY, finger_pitch_deg=pitch))
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
        SimulatedRig(_coarse(finger_identity=identity)).finger_truth()
        for identity in (IDENTITY, IDENTITY + 1, None)
    ]
    both = normals[0].mask & normals[1].mask & normals[2].mask
    for i, j in ((0, 1), (0, 2), (1, 2)):
        dots = np.sum(normals[i].normals_ps[both] * normals[j].normals_ps[both], axis=-1)
        assert np.median(np.degrees(np.arccos(np.clip(dots, -1, 1)))) > 2.0
    again = SimulatedRig(_coarse(finger_identity=IDENTITY)).finger_truth()
    np.testing.assert_array_equal(again.normals_ps, normals[0].normals_ps)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("finger_identity", -1, "finger_identity"),
        ("finger_identity", True, "finger_identity"),
        ("finger_identity", 2.5, "finger_identity"),
        ("finger_roll_deg", 46.0, "finger_roll_deg"),
        ("finger_yaw_deg", -91.0, "finger_yaw_deg"),
        ("finger_pitch_deg", 16.0, "finger_pitch_deg"),
        ("finger_roll_deg", float("nan"), "finger_roll_deg"),
    ],
)
def test_bad_pose_or_identity_is_refused(field, value, message):
    with pytest.raises(FingerpsDriverError, match=message):
        RigConfig(**{field: value})
