"""The simulated rig (fingerps_driver.simulation): geometry, ground truth, images, the cache."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.optimize import minimize

from fingerps_driver import simulation
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import Reflectance, RigConfig, Scene, SimulatedRig
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.lambertian import lambertian_shading


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig()


@pytest.fixture(scope="module")
def truth(rig):
    return rig.finger_truth()


def _apex_px(rig: SimulatedRig) -> tuple[int, int]:
    u, v = rig.camera.project(np.asarray(rig.config.finger.apex_optical_m))
    return round(float(u)), round(float(v))


@pytest.mark.parametrize(("bit_depth", "dtype", "top"), [(8, np.uint8, 255), (12, np.uint16, 4095)])
def test_frames_have_the_camera_shape_and_dtype(bit_depth, dtype, top):
    rig = SimulatedRig(RigConfig(sensor=simulation.SensorModel(bit_depth=bit_depth)))
    assert rig.max_value() == top
    assert rig.led_count == 7
    assert rig.camera_matrix.shape == (3, 3)
    assert rig.led_positions_optical.shape == (7, 3)
    rng = np.random.default_rng(0)
    for scene, lit in ((Scene.SPHERE, [2]), (Scene.WHITE_TARGET, [0, 3]), (Scene.EMPTY, [1])):
        frame = rig.render(scene, lit, rng=rng)
        assert frame.shape == (493, 659)
        assert frame.dtype == dtype
        assert frame.max() <= top


def test_camera_and_led_geometry(rig):
    k = rig.camera_matrix
    z = rig.config.finger.apex_optical_m[2]
    assert 0.080 <= z <= 0.100
    assert k[0, 0] == k[1, 1] == pytest.approx(z / 30e-6)
    # the field at the apex is ~20 x 15 mm
    assert rig.camera.width * z / k[0, 0] == pytest.approx(20e-3, rel=0.03)
    assert rig.camera.height * z / k[1, 1] == pytest.approx(15e-3, rel=0.03)
    ring = np.hypot(rig.led_positions_optical[:, 0], rig.led_positions_optical[:, 1])
    assert np.all((ring >= 35e-3) & (ring <= 45e-3))
    assert np.all(np.abs(rig.led_positions_optical[:, 2]) < 5e-3)
    lights = rig.light_directions_ps()
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0, atol=1e-12)
    apex = np.asarray(rig.config.finger.apex_optical_m)
    expected = optical_to_ps(rig.led_positions_optical - apex)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(lights, expected, atol=1e-12)
    assert np.all(lights[:, 2] > 0.85)  # ~20-26 deg off the optical axis
    intensities = rig.light_intensities()
    assert np.all(intensities > 0) and np.ptp(intensities) / intensities.max() > 0.1


def test_mask_is_a_silhouette_of_the_right_size(rig, truth):
    mask = truth.mask
    assert 0.2 < mask.mean() < 0.8
    # background visible on the left, right and top; the finger leaves at the bottom
    assert not mask[:, 0].any() and not mask[:, -1].any() and not mask[0].any()
    assert mask[-1].any()
    u0, v0 = _apex_px(rig)
    assert mask[v0, u0]
    points = rig.finger_points_optical()
    cols = np.flatnonzero(mask[v0])
    width = points[v0, cols.max(), 0] - points[v0, cols.min(), 0]
    assert width == pytest.approx(2 * rig.config.finger.radius_m * np.sin(np.radians(65)), rel=0.02)
    assert 13e-3 < width < 17e-3
    assert np.nanmin(truth.depth_m) == pytest.approx(rig.config.finger.apex_optical_m[2], abs=30e-6)


def test_truth_normals_are_unit_and_face_the_camera(truth):
    mask = truth.mask
    assert truth.normals_ps.dtype == np.float32 and truth.depth_m.dtype == np.float32
    n = truth.normals_ps[mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(n[:, 2] > 0.0)
    assert np.all(truth.normals_ps[~mask] == 0.0)
    assert np.all(np.isnan(truth.depth_m[~mask])) and np.all(np.isfinite(truth.depth_m[mask]))
    rho = truth.albedo[mask]
    assert 0.45 < rho.mean() < 0.55 and 0.02 < rho.std() / rho.mean() < 0.1


def test_truth_normals_match_the_depth(rig, truth):
    """Normals from finite differences of the back-projected depth agree with the truth."""
    points = rig.finger_points_optical()
    du = points[1:-1, 2:] - points[1:-1, :-2]
    dv = points[2:, 1:-1] - points[:-2, 1:-1]
    n_opt = np.cross(du, dv)  # (x right) x (y down) = towards +z; flip to face the camera
    n_ps = optical_to_ps(-n_opt / np.linalg.norm(n_opt, axis=-1, keepdims=True))
    u0, v0 = _apex_px(rig)
    window = (slice(v0 - 100, v0 + 100), slice(u0 - 100, u0 + 100))
    inner = (slice(v0 - 101, v0 + 99), slice(u0 - 101, u0 + 99))
    cos = np.sum(n_ps[inner] * truth.normals_ps[window], axis=-1)
    assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 1.0


def test_ridge_period_in_the_truth_normals(rig, truth):
    u0, v0 = _apex_px(rig)
    half = 96
    hann = np.hanning(2 * half)
    power = 0.0
    for c in (0, 1):
        win = truth.normals_ps[v0 - half : v0 + half, u0 - half : u0 + half, c].astype(float)
        power = power + np.abs(np.fft.fft2((win - win.mean()) * np.outer(hann, hann))) ** 2
    freq = np.fft.fftfreq(2 * half)
    radius = np.hypot(*np.meshgrid(freq, freq, indexing="ij")) * 2 * half
    profile = np.bincount(np.minimum(np.rint(radius).astype(int), half).ravel(), power.ravel())
    profile[:3] = 0.0
    k = int(np.argmax(profile[:half]))
    a, b, c = profile[k - 1 : k + 2]
    peak = k + 0.5 * (a - c) / (a - 2 * b + c)
    period_m = 2 * half / peak * rig.config.finger.apex_optical_m[2] / rig.camera_matrix[0, 0]
    print(f"\nridge period from the FFT {1e3 * period_m:.3f} mm")
    assert period_m == pytest.approx(rig.config.finger.ridge_period_m, rel=0.1)
    # ridge flanks tilt the normals by roughly atan(pi * height / period) ~ 17 deg
    tilt = np.degrees(np.arccos(truth.normals_ps[v0 - 20 : v0 + 20, u0 - 20 : u0 + 20, 2]))
    assert 10.0 < tilt.max() < 25.0


def test_lambertian_render_equals_the_shading_of_the_truth():
    rig = SimulatedRig(RigConfig(skin=simulation.SkinReflectance(model=Reflectance.LAMBERT),
                                 sensor=simulation.SensorModel(bit_depth=12)))
    truth = rig.finger_truth()
    mask = truth.mask
    points = rig.finger_points_optical()[mask]
    leds = rig.leds
    for k in (0, 4):
        to_led = rig.led_positions_optical[k] - points
        dist = np.linalg.norm(to_led, axis=1)
        lights = optical_to_ps(to_led / dist[:, None])
        cos_lobe = -(to_led @ leds.axes_optical[k]) / dist
        field = (leds.powers[k] * (leds.reference_distance_m / dist) ** 2
                 * cos_lobe ** leds.exponents[k])
        expected = rig.config.sensor.exposure_gain * field * lambertian_shading(
            truth.normals_ps[mask], lights, rho=truth.albedo[mask]
        )
        noiseless = rig.noiseless(Scene.FINGER, [k])
        np.testing.assert_allclose(noiseless[mask], expected, rtol=1e-4, atol=1e-6)
        assert np.all(noiseless[~mask] == 0.0)
        frame = rig.render(Scene.FINGER, [k], rng=np.random.default_rng(k))
        residual = frame[mask] / rig.max_value() - rig.config.sensor.ambient_fraction - expected
        # shot noise sigma = sqrt(signal / full_well); quantisation 1/4095
        sigma = np.sqrt(expected / rig.config.sensor.full_well_e + 1e-6 + 1 / (12 * 4095**2))
        z = residual / sigma
        assert abs(z.mean()) < 0.02 and 0.95 < z.std() < 1.05
    # the field falls off across the finger by > 10 %
    assert field.min() / field.max() < 0.9


def test_hk_adds_a_visible_but_not_dominant_single_scattering_term(rig, truth):
    lam = SimulatedRig(RigConfig(skin=simulation.SkinReflectance(model=Reflectance.LAMBERT)))
    mask = truth.mask
    hk = rig.noiseless(Scene.FINGER, [2])[mask]
    lambert = lam.noiseless(Scene.FINGER, [2])[mask]
    lit = lambert > 0.05
    ratio = np.median(hk[lit] / lambert[lit] - 1.0)
    assert 0.1 < ratio < 0.5


def test_brightness_of_the_scenes(rig):
    finger = [np.percentile(rig.noiseless(Scene.FINGER, [k]), 99.9) for k in range(7)]
    assert 0.7 < max(finger) < 0.9
    white = [rig.noiseless(Scene.WHITE_TARGET, [k]).max() for k in range(7)]
    assert 0.8 < max(white) < 0.97
    frame = rig.render(Scene.FINGER, [int(np.argmax(finger))], rng=np.random.default_rng(3))
    assert np.mean(frame == rig.max_value()) < 1e-3
    sphere = rig.render(Scene.SPHERE, [0], rng=np.random.default_rng(4))
    assert np.count_nonzero(sphere == rig.max_value()) >= 9  # a saturated highlight


def test_white_target_is_a_near_lit_flat_field(rig):
    for k in (1, 5):
        image = rig.noiseless(Scene.WHITE_TARGET, [k])
        assert image.min() > 0.0  # the target fills the frame
        # the brightest part of the field lies towards the LED's side
        u_led, v_led = rig.camera.project(rig.led_positions_optical[k] * [1, 1, 0] + [0, 0, 0.09])
        smooth = cv2.GaussianBlur(image, (0, 0), 15)
        v, u = np.unravel_index(np.argmax(smooth), smooth.shape)
        centre = np.array([329.0, 246.0])
        assert np.dot([u, v] - centre, [u_led, v_led] - centre) > 0


def _analytic_mirror_point(centre, radius, led):
    """Point of the sphere whose mirror reflection of the camera ray goes to ``led``."""

    def misfit(angles):
        theta, phi = angles
        n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)])
        p = centre + radius * n
        view = -p / np.linalg.norm(p)
        reflected = 2 * (n @ view) * n - view
        to_led = (led - p) / np.linalg.norm(led - p)
        return 1.0 - reflected @ to_led

    best = minimize(misfit, x0=[0.2, 0.0], method="Nelder-Mead",
                    options={"xatol": 1e-12, "fatol": 1e-16, "maxiter": 4000})
    theta, phi = best.x
    n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)])
    return centre + radius * n


def test_sphere_highlight_is_at_the_mirror_reflection(rig):
    centre = np.asarray(rig.config.sphere.center_optical_m)
    radius = rig.config.sphere.radius_m
    for k in range(rig.led_count):
        point = _analytic_mirror_point(centre, radius, rig.led_positions_optical[k])
        np.testing.assert_allclose(rig.sphere.specular_point(rig.led_positions_optical[k]),
                                   point, atol=1e-8)
        expected_uv = rig.camera.project(point)
        frame = rig.render(Scene.SPHERE, [k], rng=np.random.default_rng(10 + k))
        saturated = (frame == rig.max_value()).astype(np.uint8)
        count, _, stats, centroids = cv2.connectedComponentsWithStats(saturated)
        assert count == 2  # background + one blob
        assert 9 <= stats[1, cv2.CC_STAT_AREA] <= 150
        assert np.linalg.norm(centroids[1] - expected_uv) < 0.3
        # intensity-weighted centroid of the noiseless highlight
        signal = rig.noiseless(Scene.SPHERE, [k])
        vv, uu = np.nonzero(signal > 1.0)
        w = signal[vv, uu]
        np.testing.assert_allclose([np.sum(w * uu) / w.sum(), np.sum(w * vv) / w.sum()],
                                   expected_uv, atol=0.05)


def test_sphere_silhouette_shows_against_the_dark_background(rig):
    all_lit = rig.noiseless(Scene.SPHERE, range(rig.led_count))
    centre = np.asarray(rig.config.sphere.center_optical_m)
    u, v = rig.camera.project(centre)
    assert all_lit[int(v), int(u)] > 0.05
    dist = np.linalg.norm(centre)
    radius_px = np.tan(np.arcsin(rig.config.sphere.radius_m / dist)) * rig.camera_matrix[0, 0]
    assert all_lit[int(v), int(u + radius_px + 4)] == 0.0
    assert all_lit[int(v), int(u + radius_px - 4)] > 0.02


def test_dark_frame_is_near_zero(rig):
    for scene in (Scene.FINGER, Scene.EMPTY):
        dark = rig.render(scene, [], rng=np.random.default_rng(5))
        assert dark.mean() < 2.0 and dark.max() < 10
    empty = rig.render(Scene.EMPTY, range(7), rng=np.random.default_rng(6))
    assert empty.mean() < 2.0


def test_lit_leds_add_up(rig):
    together = rig.noiseless(Scene.FINGER, [1, 3, 6])
    apart = sum(rig.noiseless(Scene.FINGER, [k]) for k in (1, 3, 6))
    np.testing.assert_allclose(together, apart, rtol=1e-6, atol=1e-7)


def test_finger_shift_translates_the_image(rig):
    still = rig.noiseless(Scene.FINGER, [0])
    moved = rig.noiseless(Scene.FINGER, [0], finger_shift_px=(7.0, -4.0))
    np.testing.assert_allclose(moved[10:-10, 17:-10], still[14:-6, 10:-17], atol=1e-6)
    frame = rig.render(Scene.FINGER, [0], rng=np.random.default_rng(0),
                       finger_shift_px=(0.5, 0.25))
    assert frame.shape == still.shape


def test_render_is_seeded_and_returns_new_arrays(rig):
    a = rig.render(Scene.FINGER, [2], rng=np.random.default_rng(42))
    b = rig.render(Scene.FINGER, [2], rng=np.random.default_rng(42))
    np.testing.assert_array_equal(a, b)
    a[:] = 0
    assert rig.render(Scene.FINGER, [2], rng=np.random.default_rng(42)).any()


def test_after_warm_up_frames_come_from_the_cache(rig, monkeypatch: pytest.MonkeyPatch):
    # What a frame costs then is a benchmark figure (bench/bench_driver.py,
    # driver.render_ms.median); here: warm_up leaves nothing to trace or shade.
    rig.warm_up([Scene.FINGER])

    def recomputed(*args: object) -> None:
        raise AssertionError("a frame was shaded again after warm_up")

    monkeypatch.setattr(rig, "_finger_radiance", recomputed)
    monkeypatch.setattr(rig, "_finger_surface", recomputed)
    rng = np.random.default_rng(0)
    for k in range(rig.led_count):
        frame = rig.render(Scene.FINGER, [k], rng=rng)
        assert frame.shape == (rig.camera.height, rig.camera.width) and frame.any()
    assert rig.render(Scene.FINGER, list(range(rig.led_count)), rng=rng).any()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"sensor": simulation.SensorModel(bit_depth=10)},
        {"leds": simulation.LedLayout(powers=(1.0, 1.0))},
        {"finger": simulation.FingertipShape(ridge_period_m=0.0)},
        {"finger": simulation.FingertipShape(ridge_height_m=400e-6)},
        {"sphere": simulation.MirrorSphere(center_optical_m=(0.0, 0.0, 0.001))},
        {"camera": simulation.PinholeCamera(width=8)},
    ],
)
def test_bad_configurations_are_refused(kwargs):
    with pytest.raises(FingerpsDriverError, match="RigConfig"):
        RigConfig(**kwargs)


def test_bad_render_arguments_are_refused(rig):
    rng = np.random.default_rng(0)
    with pytest.raises(FingerpsDriverError):
        rig.render(Scene.FINGER, [7], rng=rng)
    with pytest.raises(FingerpsDriverError):
        rig.render(Scene.FINGER, [1, 1], rng=rng)
    with pytest.raises(FingerpsDriverError):
        rig.render("finger", [1], rng=rng)


def test_a_burst_is_one_frame_per_led_with_the_noise_seeded_as_said() -> None:
    rig = SimulatedRig(RigConfig(camera=simulation.PinholeCamera(width=64, height=48)))
    by_led = [rig.render(Scene.FINGER, [k], rng=np.random.default_rng(5 + k))
              for k in range(rig.led_count)]
    assert np.array_equal(rig.render_burst(Scene.FINGER, seed=5), np.stack(by_led))
    by_led = [rig.render(Scene.FINGER, [k], rng=np.random.default_rng([3, 1, k]))
              for k in range(rig.led_count)]
    assert np.array_equal(rig.render_burst(Scene.FINGER, seed=[3, 1]), np.stack(by_led))
    shared = np.random.default_rng(9)
    by_led = [rig.render(Scene.FINGER, [k], rng=shared) for k in range(rig.led_count)]
    assert np.array_equal(rig.render_burst(Scene.FINGER, rng=np.random.default_rng(9)),
                          np.stack(by_led))
    for seed, rng in ((None, None), (1, np.random.default_rng(1))):
        with pytest.raises(ValueError, match="one of seed and rng"):
            rig.render_burst(Scene.FINGER, seed=seed, rng=rng)
