"""Tests of fingerps_recon.surface.integration on analytic surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_driver.simulation import SimulatedRig
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.pixel_rays import pixel_rays_optical
from fingerps_recon.surface.integration import (
    IntegrationMethod,
    depth_to_points,
    height_to_distance,
    integrate_normals,
    integrate_normals_perspective,
)

PIXEL = 2e-5  # metres per pixel


def _normals_of(height_fn, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Analytic normals (PS frame) and heights of h(x, y), x = u * PIXEL, y = -v * PIXEL."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    x, y = u * PIXEL, -v * PIXEL
    h, hx, hy = height_fn(x, y)
    n = np.stack([-hx, -hy, np.ones_like(h)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True), h


def _zero_mean(h: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, h - h[mask].mean(), np.nan)


def _sphere_cap(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals, heights and mask (0.8 of the radius) of a sphere cap of radius 60 px centred
    at pixel (u, v) = (70, 60)."""
    r_m = 60 * PIXEL
    c = np.array([70 * PIXEL, -60 * PIXEL])

    def sphere(x, y):
        d2 = (x - c[0]) ** 2 + (y - c[1]) ** 2
        z = np.sqrt(np.clip(r_m**2 - d2, 1e-30, None))
        return z, -(x - c[0]) / z, -(y - c[1]) / z

    normals, h = _normals_of(sphere, shape)
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    return normals, h, np.hypot(u - 70, v - 60) < 0.8 * 60


def test_tilted_plane_is_exact_and_axes_are_right() -> None:
    a, b = 0.3, -0.2  # dh/dx, dh/dy with y up
    normals, h = _normals_of(lambda x, y: (a * x + b * y, a + 0 * x, b + 0 * x), (50, 70))
    mask = np.ones(h.shape, dtype=bool)
    mask[:5, :5] = False
    got = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got[mask], _zero_mean(h, mask)[mask], atol=1e-9)
    assert np.all(np.isnan(got[~mask]))
    # Height grows to the right (a > 0) and towards the top of the image (b < 0: downwards).
    assert got[25, 60] > got[25, 10]
    assert got[45, 35] > got[10, 35]


def test_sphere_cap_with_mask() -> None:
    normals, h, mask = _sphere_cap((121, 141))
    got = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    truth = _zero_mean(h, mask)
    span = np.ptp(truth[mask])
    err = np.abs(got[mask] - truth[mask])
    assert err.max() < 0.01 * span
    assert np.sqrt(np.mean(err**2)) < 0.002 * span
    assert got[60, 70] > 0 > got[60, 30]  # a bump: centre up, rim down
    assert abs(float(np.nanmean(got))) < 1e-9


def test_gaussian_bump_with_hole_and_second_component() -> None:
    shape = (150, 200)
    s = 25 * PIXEL

    def bump(x, y):
        e = 3e-4 * np.exp(-((x - 100 * PIXEL) ** 2 + (y + 75 * PIXEL) ** 2) / (2 * s**2))
        return e, -e * (x - 100 * PIXEL) / s**2, -e * (y + 75 * PIXEL) / s**2

    normals, h = _normals_of(bump, shape)
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    big = (np.abs(u - 100) < 80) & (np.abs(v - 75) < 60) & (np.hypot(u - 130, v - 75) > 6)
    small = (u > 185) & (v > 130)  # a separate 14 x 19 patch, solved on its own
    mask = big | small
    got = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    for part in (big, small):
        truth = h[part] - h[part].mean()
        assert abs(float(got[part].mean())) < 1e-10  # zero mean per component
        assert np.abs(got[part] - truth).max() < 0.01 * 3e-4
    assert got[75, 100] > 2e-4  # the peak, relative to the component's mean


def test_direct_fallback_matches_the_iterative_solve() -> None:
    normals, h = _normals_of(
        lambda x, y: (
            np.sin(x / (9 * PIXEL)) * 1e-4,
            np.cos(x / (9 * PIXEL)) / (9 * PIXEL) * 1e-4,
            0 * x,
        ),
        (100, 120),
    )
    v, u = np.mgrid[0:100, 0:120]
    mask = np.hypot(u - 60, v - 50) < 45
    iterative = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    direct = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL, max_iter=1)
    np.testing.assert_allclose(iterative[mask], direct[mask], atol=1e-5 * 2e-4)
    comb = ((u % 4) == 0) | (v < 3)  # a comb: slow for CG, cheap for the direct solver
    got = integrate_normals(normals, mask=comb, pixel_size_m=PIXEL)
    truth = _zero_mean(h, comb)
    assert np.abs(got[comb] - truth[comb]).max() < 0.02 * 2e-4


def test_degenerate_masks_and_bad_normals() -> None:
    normals = np.zeros((20, 30, 3))
    normals[..., 2] = 1.0
    normals[5, 5] = 0.0  # no normal: zero slope, not NaN
    normals[6, 6] = np.nan
    mask = np.zeros((20, 30), dtype=bool)
    assert np.all(np.isnan(integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)))
    mask[2:15, 2:20] = True
    mask[18, 25] = True  # a single pixel
    got = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    assert np.all(np.isfinite(got[mask]))
    np.testing.assert_allclose(got[mask], 0.0, atol=1e-12)


@pytest.mark.parametrize(
    ("normals", "mask", "kwargs"),
    [
        (np.zeros((4, 5)), np.ones((4, 5), bool), {}),
        (np.zeros((4, 5, 3)), np.ones((4, 6), bool), {}),
        (np.zeros((4, 5, 3)), np.ones((4, 5)), {}),
        (np.zeros((4, 5, 3)), np.ones((4, 5), bool), {"pixel_size_m": 0.0}),
        (np.zeros((4, 5, 3)), np.ones((4, 5), bool), {"min_nz": 0.0}),
    ],
)
def test_integrate_bad_inputs_raise(normals: np.ndarray, mask: np.ndarray, kwargs: dict) -> None:
    with pytest.raises(FingerpsReconError):
        integrate_normals(normals, mask=mask, **{"pixel_size_m": PIXEL, **kwargs})


def test_height_to_distance() -> None:
    h = np.array([[0.001, np.nan], [-0.002, 0.0]])
    d = height_to_distance(h, working_distance_m=0.05)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d, [[0.049, np.nan], [0.052, 0.05]], rtol=1e-6)
    with pytest.raises(FingerpsReconError):
        height_to_distance(h, working_distance_m=-1.0)


def test_depth_to_points_back_projects_and_indexes() -> None:
    k = np.array([[800.0, 0.0, 30.0], [0.0, 820.0, 20.0], [0.0, 0.0, 1.0]])
    depth = np.full((40, 60), 0.05)
    depth[3, 4] = np.nan
    depth[5, 6] = -1.0
    mask = np.zeros((40, 60), dtype=bool)
    mask[:10, :10] = True
    mask[30, 50] = True
    points, index = depth_to_points(depth, mask, camera_matrix=k)
    assert points.dtype == np.float32 and points.shape == (100 - 2 + 1, 3)
    assert index.dtype == np.int64 and index.shape == (points.shape[0],)
    v, u = np.divmod(index, 60)
    assert np.all(mask[v, u])
    # Re-projection gives the pixel back.
    np.testing.assert_allclose(k[0, 0] * points[:, 0] / points[:, 2] + k[0, 2], u, atol=1e-3)
    np.testing.assert_allclose(k[1, 1] * points[:, 1] / points[:, 2] + k[1, 2], v, atol=1e-3)
    np.testing.assert_allclose(points[:, 2], 0.05, rtol=1e-6)
    # The pixel at (u, v) = (50, 30) is right of and below the principal point: x > 0, y > 0.
    p = points[index == 30 * 60 + 50][0]
    assert p[0] > 0 and p[1] > 0
    intensity = np.arange(40 * 60, dtype=np.float32).reshape(40, 60)
    np.testing.assert_array_equal(intensity.ravel()[index], v * 60 + u)


def test_depth_to_points_bad_inputs_raise() -> None:
    with pytest.raises(FingerpsReconError, match="camera_matrix"):
        depth_to_points(np.ones((4, 5)), np.ones((4, 5), bool), camera_matrix=np.eye(2))
    with pytest.raises(FingerpsReconError, match="mask"):
        depth_to_points(np.ones((4, 5)), np.ones((4, 6), bool), camera_matrix=np.eye(3))


# ----------------------------------------------------------------- FAST vs EXACT


def test_fast_is_the_default_and_agrees_with_exact() -> None:
    normals, _, mask = _sphere_cap((121, 141))
    mask[50:60, 20:30] = False  # a hole
    mask[5:10, 130:136] = True  # a second component
    default = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    fast = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL, method=IntegrationMethod.FAST)
    exact = integrate_normals(
        normals, mask=mask, pixel_size_m=PIXEL, method=IntegrationMethod.EXACT
    )
    np.testing.assert_array_equal(default, fast)
    assert fast.dtype == exact.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(fast), ~mask)
    span = np.ptp(exact[mask])
    # Relative residual 1e-4 against 1e-6: the heights agree to ~1e-5 of their span.
    assert np.abs(fast[mask] - exact[mask]).max() < 1e-4 * span
    # Zero mean on each component, as EXACT.
    second = np.zeros_like(mask)
    second[5:10, 130:136] = True
    assert abs(float(fast[second].mean())) < 1e-6 * span
    assert abs(float(fast[mask & ~second].mean())) < 1e-6 * span


def test_fast_falls_back_to_exact_where_it_stalls() -> None:
    normals, _, _ = _sphere_cap((121, 141))
    v, u = np.mgrid[0:121, 0:141]
    comb = ((u % 4) == 0) | (v < 3)  # CG with the rectangle preconditioner stalls here
    fast = integrate_normals(normals, mask=comb, pixel_size_m=PIXEL)
    exact = integrate_normals(
        normals, mask=comb, pixel_size_m=PIXEL, method=IntegrationMethod.EXACT
    )
    np.testing.assert_allclose(fast[comb], exact[comb], atol=1e-6 * np.ptp(exact[comb]))


def test_method_must_be_an_integration_method() -> None:
    normals, _, mask = _sphere_cap((31, 41))
    with pytest.raises(FingerpsReconError, match="IntegrationMethod"):
        integrate_normals(normals, mask=mask, pixel_size_m=PIXEL, method="fast")


# ----------------------------------------------------------------- perspective

#: The rig's intrinsics (fingerps_driver.simulation.RigConfig defaults), 659 x 493 pixels.
K_RIG = np.array([[3000.0, 0.0, 329.0], [0.0, 3000.0, 246.0], [0.0, 0.0, 1.0]])


def _perspective_sphere(
    k: np.ndarray, centre: tuple[float, float, float], radius: float, *, min_cos: float = 0.3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PS-frame normals, optical depth and mask of a sphere (optical frame) seen by K."""
    v, u = np.mgrid[0:493, 0:659].astype(np.float64)
    fx, s, cx = k[0]
    fy, cy = k[1, 1], k[1, 2]
    y_n = (v - cy) / fy
    x_n = (u - cx - s * y_n) / fx
    ray = np.stack([x_n, y_n, np.ones_like(x_n)], axis=-1)
    c = np.asarray(centre)
    rc = ray @ c
    rr = np.sum(ray * ray, axis=-1)
    disc = rc**2 - rr * (c @ c - radius**2)
    hit = disc > 0
    t = (rc - np.sqrt(np.where(hit, disc, 0.0))) / rr  # the near intersection; z = t
    points = t[..., None] * ray
    n_optical = (points - c) / radius
    cos_view = -np.sum(n_optical * points, axis=-1) / np.linalg.norm(points, axis=-1)
    mask = hit & (cos_view > min_cos)
    normals = np.where(mask[..., None], n_optical * np.array([1.0, -1.0, -1.0]), 0.0)
    return normals, np.where(mask, t, np.nan), mask


@pytest.mark.parametrize("method", list(IntegrationMethod))
@pytest.mark.parametrize(
    ("k", "centre", "radius"),
    [
        (K_RIG, (0.5e-3, -1.0e-3, 0.090), 3e-3),
        (K_RIG, (-3.0e-3, 2.0e-3, 0.070), 2.5e-3),  # off axis: orthography would be 7 % off
        (np.array([[2800.0, 15.0, 320.0], [0.0, 3100.0, 250.0], [0.0, 0.0, 1.0]]),
         (0.5e-3, -1.0e-3, 0.090), 3e-3),  # fx != fy and skew
    ],
)
def test_perspective_sphere(
    k: np.ndarray, centre: tuple[float, float, float], radius: float, method: IntegrationMethod
) -> None:
    normals, depth, mask = _perspective_sphere(k, centre, radius)
    working_distance = float(np.exp(np.mean(np.log(depth[mask]))))
    got = integrate_normals_perspective(
        normals, mask=mask, camera_matrix=k, working_distance_m=working_distance, method=method
    )
    assert got.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(got), ~mask)
    # Mean log-depth is log(working distance).
    assert abs(np.mean(np.log(got[mask].astype(np.float64))) - np.log(working_distance)) < 1e-6
    relative = np.abs(got[mask] / depth[mask] - 1)
    assert relative.max() < 1e-2  # the bound asked for; measured ~1e-5
    assert relative.max() < 1e-4
    # The relief (a few mm) itself to 0.1 %; measured 5e-4 at the steep rim.
    assert np.abs(got[mask] - depth[mask]).max() < 1e-3 * np.ptp(depth[mask])
    # Back-projected, the points lie on the sphere.
    points, _ = depth_to_points(got, mask, camera_matrix=k)
    radii = np.linalg.norm(points - np.asarray(centre), axis=1)
    assert np.abs(radii - radius).max() < 1e-3 * radius


def test_perspective_scale_follows_the_working_distance() -> None:
    normals, _, mask = _perspective_sphere(K_RIG, (0.0, 0.0, 0.09), 3e-3)
    near = integrate_normals_perspective(
        normals, mask=mask, camera_matrix=K_RIG, working_distance_m=0.05
    )
    far = integrate_normals_perspective(
        normals, mask=mask, camera_matrix=K_RIG, working_distance_m=0.10
    )
    np.testing.assert_allclose(far[mask], 2 * near[mask], rtol=1e-5)
    empty = np.zeros_like(mask)
    assert np.all(np.isnan(integrate_normals_perspective(
        normals, mask=empty, camera_matrix=K_RIG, working_distance_m=0.05)))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"camera_matrix": np.eye(2)},
        {"camera_matrix": np.diag([-1.0, 1.0, 1.0])},
        {"working_distance_m": 0.0},
        {"working_distance_m": float("nan")},
        {"min_nz": 0.0},
        {"method": "exact"},
    ],
)
def test_perspective_bad_inputs_raise(kwargs: dict) -> None:
    args = {"mask": np.ones((4, 5), bool), "camera_matrix": K_RIG, "working_distance_m": 0.09}
    with pytest.raises(FingerpsReconError):
        integrate_normals_perspective(np.zeros((4, 5, 3)), **{**args, **kwargs})


def test_simulated_finger_depth_from_true_normals() -> None:
    """The simulated rig's finger from its true normals: perspective integration recovers
    the depth to ~1 um RMS (after the free scale); orthographic integration is ~110 um off
    (the finger spans 90-95 mm at 90 mm); FAST and EXACT agree to far below either."""
    rig = SimulatedRig()
    truth = rig.finger_truth()
    mask = truth.mask
    true_depth = truth.depth_m[mask].astype(np.float64)
    k = rig.camera_matrix

    def rms_um(err: np.ndarray) -> float:
        return float(np.sqrt(np.mean(err**2)) * 1e6)

    results = {}
    for method in IntegrationMethod:
        depth = integrate_normals_perspective(
            truth.normals_ps, mask=mask, camera_matrix=k, working_distance_m=0.09, method=method
        )[mask].astype(np.float64)
        scale = np.exp(np.mean(np.log(true_depth) - np.log(depth)))
        results[method] = scale * depth
        assert rms_um(scale * depth - true_depth) < 3.0  # measured 1.04 um
    assert rms_um(results[IntegrationMethod.FAST] - results[IntegrationMethod.EXACT]) < 0.1
    height = integrate_normals(truth.normals_ps, mask=mask, pixel_size_m=0.09 / k[0, 0])
    ortho = height_to_distance(height, working_distance_m=0.09)[mask] - true_depth
    assert rms_um(ortho - ortho.mean()) > 50.0  # measured 110 um: the perspective matters


@pytest.mark.parametrize("bad", [np.nan, np.inf, -3000.0])
def test_a_bad_camera_matrix_is_refused_in_one_line(bad: float) -> None:
    k = np.array([[3000.0, 0.0, 20.0], [0.0, 3000.0, 20.0], [0.0, 0.0, 1.0]])
    k[0, 0] = bad
    normals = np.zeros((40, 40, 3), np.float32)
    normals[..., 2] = 1.0
    with pytest.raises(FingerpsReconError, match="finite 3x3 intrinsic matrix") as info:
        integrate_normals_perspective(normals, mask=np.ones((40, 40), bool), camera_matrix=k,
                                      working_distance_m=0.09)
    assert "\n" not in str(info.value)
    with pytest.raises(FingerpsReconError, match="finite 3x3 intrinsic matrix") as info:
        pixel_rays_optical(k, (4, 4))
    assert "\n" not in str(info.value)
