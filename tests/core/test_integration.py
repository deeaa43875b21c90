"""Tests of fingerps_recon.surface.integration (and the modules of its solvers) on analytic
surfaces."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import scipy.fft
import scipy.ndimage

from fingerps_driver.simulation import SimulatedRig
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.pixel_rays import pixel_rays_optical
from fingerps_recon.surface import integration_preconditioner
from fingerps_recon.surface.back_projection import depth_to_points, height_to_distance
from fingerps_recon.surface.integration import (
    IntegrationMethod,
    integrate_normals,
    integrate_normals_perspective,
)
from fingerps_recon.surface.integration_cg_kernel import outline_spectrum
from fingerps_recon.surface.integration_polynomial_kernel import column_moments
from fingerps_recon.surface.integration_polynomials import (
    BASIS_A,
    BASIS_B,
    POLY_DEGREE,
    poly_tables,
)
from fingerps_recon.surface.integration_preconditioner import (
    column_pivots,
    cosines,
    precondition,
)
from fingerps_recon.surface.integration_rhs_kernel import assemble_rhs
from fingerps_recon.surface.integration_solution_kernel import finish_runs
from fingerps_recon.surface.integration_steps import orthographic_steps
from fingerps_recon.surface.integration_topology_kernel import run_topology

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


@pytest.fixture
def applications(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the FAST solver's preconditioner applications (one entry per call)."""
    calls: list[int] = []
    original = integration_preconditioner.precondition

    def counted(buf: np.ndarray, pivots: tuple[np.ndarray, np.ndarray], **kwargs: bool) -> None:
        calls.append(1)
        original(buf, pivots, **kwargs)

    monkeypatch.setattr(integration_preconditioner, "precondition", counted)
    return calls


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


def test_tilted_plane_is_exact_and_axes_are_right(applications: list[int]) -> None:
    a, b = 0.3, -0.2  # dh/dx, dh/dy with y up
    normals, h = _normals_of(lambda x, y: (a * x + b * y, a + 0 * x, b + 0 * x), (50, 70))
    mask = np.ones(h.shape, dtype=bool)
    mask[:5, :5] = False
    got = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    # The polynomial start is the plane itself: no iteration (preconditioner application).
    assert applications == []
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
    # FAST to a relative residual of 1e-6 (its float32 arithmetic reaches ~1e-7 here): the
    # heights agree with the direct solve to ~1e-7 of the 2e-4 amplitude (measured 4e-8).
    iterative = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL, tol=1e-6)
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


def test_depth_to_points_with_skew_reprojects_and_leaves_out_infinite_depths() -> None:
    k = np.array([[800.0, 12.0, 30.0], [0.0, 820.0, 20.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.08, 0.1, (40, 60)).astype(np.float32)
    depth[7, 8] = np.inf
    mask = rng.random((40, 60)) < 0.7
    mask[7, 8] = True
    points, index = depth_to_points(depth, mask, camera_matrix=k)
    expected = np.flatnonzero(mask & np.isfinite(depth))
    np.testing.assert_array_equal(index, expected)  # raster order, the infinite one left out
    v, u = np.divmod(index, 60)
    x, y, z = points.T.astype(np.float64)
    np.testing.assert_allclose(z, depth[v, u], rtol=0)
    # u = fx x / z + s y / z + cx, v = fy y / z + cy
    np.testing.assert_allclose(k[0, 0] * x / z + k[0, 1] * y / z + k[0, 2], u, atol=1e-3)
    np.testing.assert_allclose(k[1, 1] * y / z + k[1, 2], v, atol=1e-3)


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
    # Relative residual FAST_TOL = 3e-3 against 1e-6: the heights agree to ~1e-4 of their
    # span (measured 1.3e-4 at most, 1.3e-5 RMS: the polynomial correction at the end takes
    # out most of the smooth error the residual leaves).
    error = np.abs(fast[mask] - exact[mask])
    assert error.max() < 1e-3 * span
    assert np.sqrt(np.mean(error**2)) < 1e-4 * span
    # To a relative residual of 1e-5 they agree ten times closer (measured 3.9e-6).
    tight = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL, tol=1e-5)
    assert np.abs(tight[mask] - exact[mask]).max() < 2e-5 * span
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


def test_simulated_finger_depth_from_true_normals(applications: list[int]) -> None:
    """The simulated rig's finger from its true normals: perspective integration recovers
    the depth to ~1 um RMS (after the free scale); orthographic integration is ~110 um off
    (the finger spans 90-95 mm at 90 mm); FAST and EXACT agree to far below either, FAST
    with 3 preconditioner applications (its relative residual is ~1e-3 after 3, ~8e-3
    after 2, against FAST_TOL = 3e-3)."""
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
        if method is IntegrationMethod.FAST:
            assert len(applications) == 3
    # measured 0.07 um
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


# ----------------------------------------------------------------- FAST solver's parts


def _rectangle_pseudo_inverse(r: np.ndarray) -> np.ndarray:
    """L^+ r in float64 by a 2-D DCT-II, L the rectangle's Neumann Laplacian."""
    h, w = r.shape
    ev = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + (
        2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    ev[0, 0] = 1.0
    inverse = 1.0 / ev
    inverse[0, 0] = 0.0  # the constant is free
    spectrum = scipy.fft.dctn(r.astype(np.float64), norm="ortho") * inverse
    return scipy.fft.idctn(spectrum, norm="ortho")


@pytest.mark.parametrize("shape", [(1, 8), (2, 5), (13, 20), (37, 50)])
def test_the_preconditioner_is_the_rectangles_pseudo_inverse(shape: tuple[int, int]) -> None:
    """Row DCTs and column solves give the 2-D DCT's L^+; and the row transform of a few
    pixels summed directly gives the same as pocketfft's."""
    rng = np.random.default_rng(7)
    r = rng.standard_normal(shape).astype(np.float32)
    got = r.copy()
    pivots = column_pivots(shape)
    precondition(got, pivots)
    ref = _rectangle_pseudo_inverse(r)
    # float32: a few roundings (2^-24 each) per row transform and per step of the column
    # recurrence, relative to the largest output value (L^+ amplifies the smooth modes and
    # their rounding alike); measured <= 2.4e-7.
    assert np.abs(got - ref).max() < 2e-6 * np.abs(ref).max()

    h, w2 = shape
    n = min(7, h * w2)
    pixels = rng.choice(h * w2, n, replace=False)
    rows, cols = (pixels // w2).astype(np.int32), (pixels % w2).astype(np.int32)
    values = rng.standard_normal(n).astype(np.float32)
    sparse = np.zeros(shape, np.float32)
    outline_spectrum(values, sparse, rows, cols, n, cosines(w2))
    precondition(sparse, pivots, transformed=True)
    dense = np.zeros(shape, np.float32)
    dense[rows, cols] = values
    precondition(dense, pivots)
    assert np.abs(sparse - dense).max() < 2e-6 * np.abs(dense).max()  # measured 1.5e-7


def test_the_cosine_table_is_the_orthonormal_dct() -> None:
    w2 = 24
    # rows: the DCT of each unit vector; float32 rounding of values <= 1: half an ulp, 6e-8
    np.testing.assert_allclose(cosines(w2), scipy.fft.dct(np.eye(w2), norm="ortho", axis=1),
                               atol=1e-7)


def test_runs_give_the_outline_components_and_gram_matrix() -> None:
    """The kernels' rows of runs against direct numpy definitions on a small mask: two
    components, a hole, a pixel alone, runs touching the box's edges."""
    mask = np.zeros((11, 14), dtype=bool)
    mask[1:9, 0:9] = True
    mask[4:6, 3:5] = False       # a hole
    mask[2:10, 11:14] = True     # a second component, on the box's right edge
    mask[0:2, 12] = True         # joined to it from the top row
    mask[10, 1] = True           # a pixel alone
    normals = np.zeros((*mask.shape, 3), np.float32)
    yy, xx = np.mgrid[0:11, 0:14]
    normals[..., 0] = 0.1 * np.sin(xx / 3.0)
    normals[..., 1] = 0.1 * np.cos(yy / 2.0)
    normals[..., 2] = 1.0
    h, w = mask.shape
    w2 = 16  # two padding columns: the second component's right end is outline
    steps = orthographic_steps(normals, (slice(0, h), slice(0, w)), min_nz=0.1)
    poly = poly_tables(h, w)
    b = np.empty((h, w2), np.float32)
    col_moments = np.empty((POLY_DEGREE + 1, w))
    room = h * (w // 2 + 1)
    run_start, run_stop = np.empty(room, np.int32), np.empty(room, np.int32)
    row_first = np.empty(h + 1, np.int32)
    inside = mask.view(np.uint8)
    n_runs, b_norm2 = assemble_rhs(
        steps.normals, inside, 0, 0, h, w, steps.x_n, steps.y_n, steps.skew, steps.min_nz,
        steps.fx, steps.fy, poly.row_powers, b, col_moments, run_start, run_stop, row_first)
    labels = np.empty(n_runs, np.int32)
    outline_rows, outline_cols = np.empty(h * w, np.int32), np.empty(h * w, np.int32)
    n_basis = BASIS_A.size
    gram = np.empty((n_basis, n_basis))
    degree = POLY_DEGREE
    mask_moments = np.empty((degree + 1, degree + 1))
    segments = np.empty((2, 2, w + 1), np.int32)
    n_comp, n_out = run_topology(
        run_start[:n_runs], run_stop[:n_runs], row_first, w2, poly.pair_prefix,
        poly.power_prefix, poly.row_powers, poly.row_steps, BASIS_A, BASIS_B, labels,
        outline_rows, outline_cols, gram, mask_moments, segments[0], segments[1])

    # Runs: the mask row by row (exact: integers).
    rebuilt = np.zeros_like(mask)
    for r in range(h):
        for i in range(row_first[r], row_first[r + 1]):
            rebuilt[r, run_start[i]:run_stop[i]] = True
    np.testing.assert_array_equal(rebuilt, mask)
    # Components: scipy's 4-connected labels, numbered in raster order of first pixel.
    ref_labels, ref_count = scipy.ndimage.label(mask)
    assert n_comp == ref_count == 3
    for r in range(h):
        for i in range(row_first[r], row_first[r + 1]):
            assert ref_labels[r, run_start[i]] - 1 == labels[i]
    # Outline: mask pixels with a 4-neighbour in the h x w2 rectangle outside the mask.
    padded = np.zeros((h, w2), bool)
    padded[:, :w] = mask
    outside = np.zeros_like(padded)
    outside[:, 1:] |= ~padded[:, :-1]
    outside[:, :-1] |= ~padded[:, 1:]
    outside[1:] |= ~padded[:-1]
    outside[:-1] |= ~padded[1:]
    ref_outline = padded & outside
    got_outline = np.zeros_like(padded)
    got_outline[outline_rows[:n_out], outline_cols[:n_out]] = True
    np.testing.assert_array_equal(got_outline, ref_outline)
    assert n_out == ref_outline.sum()  # each once
    # b = D^T g: float32 sums of at most four means of two steps (a few ulps of |b|).
    du = np.where(mask, -normals[..., 0] / normals[..., 2], 0.0)
    dv = np.where(mask, normals[..., 1] / normals[..., 2], 0.0)
    hor = mask[:, :-1] & mask[:, 1:]
    ver = mask[:-1] & mask[1:]
    g_h = np.where(hor, 0.5 * (du[:, :-1] + du[:, 1:]), 0.0)
    g_v = np.where(ver, 0.5 * (dv[:-1] + dv[1:]), 0.0)
    ref_b = np.zeros((h, w))
    ref_b[:, 1:] += g_h
    ref_b[:, :-1] -= g_h
    ref_b[1:] += g_v
    ref_b[:-1] -= g_v
    np.testing.assert_allclose(b[:, :w], ref_b, atol=1e-6 * np.abs(ref_b).max())
    assert np.all(b[:, w:] == 0)
    np.testing.assert_allclose(b_norm2, np.sum(ref_b**2), rtol=1e-5)
    # Gram matrix V^T A V of the monomials, summed directly over the edges (float64 sums
    # of a few hundred terms: ~1e-14 of the largest entry; the prefix sums' differences
    # cancel ~1e-16 of w terms).
    s = poly.col_powers[1]
    t = poly.row_powers[:, 1]
    basis = np.array([np.outer(t**b, s**a) for a, b in zip(BASIS_A, BASIS_B, strict=True)])
    steps_h = (basis[:, :, 1:] - basis[:, :, :-1])[:, hor]
    steps_v = (basis[:, 1:, :] - basis[:, :-1, :])[:, ver]
    ref_gram = steps_h @ steps_h.T + steps_v @ steps_v.T
    np.testing.assert_allclose(gram, ref_gram, atol=1e-12 * np.abs(ref_gram).max())
    # The mask's moments: sums of s^a t^b over its pixels (float64, prefix-sum differences).
    s_all = poly.col_powers[1][None, :] * np.ones((h, 1))
    t_all = poly.row_powers[:, 1][:, None] * np.ones((1, w))
    ref_moments = np.array([[np.sum((s_all**a * t_all**b)[mask]) for b in range(degree + 1)]
                            for a in range(degree + 1)])
    np.testing.assert_allclose(mask_moments, ref_moments, atol=1e-12 * mask.sum())
    # Moments V^T b (float64 sums of float32 b times powers).
    moments = np.empty(n_basis)
    column_moments(col_moments, poly.col_powers, BASIS_A, BASIS_B, moments)
    np.testing.assert_allclose(moments, basis.reshape(n_basis, -1) @ b[:, :w].ravel(),
                               atol=1e-12 * np.abs(b).sum())


@pytest.mark.parametrize("reach", [0.04, 20.0])
def test_the_exponential_is_within_an_ulp_of_numpys(reach: float) -> None:
    """finish_runs' exponential (as write_solution's), in float64 rounded once to float32:
    with |t| <= 0.05, Taylor to t^5 (remainder < 2.2e-11); else Taylor to t^8 on
    |t| <= 0.35 (remainder < 2.2e-10), the exponent halved m times and the result squared m
    times (the remainder doubles each time: m = 6 for |t| <= 20.5 gives 1.4e-8). Within one
    float32 ulp (at most 2^-23 = 1.2e-7 relative) of the correctly rounded exp; asserted
    with twice that."""
    values = np.linspace(-reach, reach, 401) + 0.5
    out = np.full((3, values.size + 2), np.nan, np.float32)
    out[1, 1:-1] = values
    run_start, run_stop = np.array([1], np.int32), np.array([values.size + 1], np.int32)
    row_first = np.array([0, 0, 1, 1], np.int32)
    labels = np.zeros(1, np.int32)
    finish_runs(out, 0, 0, 3, values.size + 2, run_start, run_stop, row_first, labels,
                np.array([0.5]), 1.0, -2.0, True)
    expected = np.exp(values.astype(np.float32).astype(np.float64) - 0.5 - 2.0)
    np.testing.assert_allclose(out[1, 1:-1], expected.astype(np.float32), rtol=2.4e-7)
    assert np.isnan(out[0]).all() and np.isnan(out[2]).all()
    assert np.isnan(out[1, [0, -1]]).all()


def test_perspective_components_each_get_the_working_distance() -> None:
    """Two spheres, two components: the geometric mean depth of each is the working
    distance (float32 depths: a relative rounding of 6e-8 each, in the mean of the logs)."""
    a_normals, a_depth, a_mask = _perspective_sphere(K_RIG, (-2.0e-3, 0.0, 0.090), 1.5e-3)
    b_normals, b_depth, b_mask = _perspective_sphere(K_RIG, (2.5e-3, 1.0e-3, 0.080), 1.2e-3)
    assert not np.any(a_mask & b_mask)
    normals = np.where(a_mask[..., None], a_normals, b_normals)
    mask = a_mask | b_mask
    got = integrate_normals_perspective(normals, mask=mask, camera_matrix=K_RIG,
                                        working_distance_m=0.085)
    for part, depth in ((a_mask, a_depth), (b_mask, b_depth)):
        logs = np.log(got[part].astype(np.float64))
        assert abs(logs.mean() - np.log(0.085)) < 1e-6  # measured 2e-10
        # the shape within each: relative depth to 1e-4 (measured 2.4e-5)
        relative = got[part] / depth[part]
        assert np.ptp(relative) < 1e-4 * relative.mean()


def test_the_solver_arrays_kept_between_calls_change_no_result() -> None:
    """The per-thread arrays (sized for the largest box so far): a small box after a big
    one, and another thread, give bit-identical results (the same computation)."""
    big_normals, _, big_mask = _perspective_sphere(K_RIG, (0.5e-3, -1.0e-3, 0.090), 3e-3)
    small_normals, _, small_mask = _perspective_sphere(K_RIG, (-3.0e-3, 2.0e-3, 0.070),
                                                       1.0e-3)

    def depths() -> tuple[np.ndarray, np.ndarray]:
        args = {"camera_matrix": K_RIG, "working_distance_m": 0.09}
        return (integrate_normals_perspective(small_normals, mask=small_mask, **args),
                integrate_normals_perspective(big_normals, mask=big_mask, **args))

    small_first, big = depths()
    small_after, big_again = depths()
    np.testing.assert_array_equal(small_first, small_after)
    np.testing.assert_array_equal(big, big_again)
    results: list[tuple[np.ndarray, np.ndarray]] = []
    threads = [threading.Thread(target=lambda: results.append(depths())) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for small, big_other in results:
        np.testing.assert_array_equal(small, small_first)
        np.testing.assert_array_equal(big_other, big)


def test_a_full_rectangle_is_solved_by_the_first_application(applications: list[int]) -> None:
    """With the mask filling its rectangle (and 24 columns, an FFT length: no padding) there
    is no outline: the first preconditioner application is the solution."""
    normals, _ = _normals_of(
        lambda x, y: (np.sin(x / (7 * PIXEL)) * np.cos(y / (5 * PIXEL)) * 1e-4,
                      np.cos(x / (7 * PIXEL)) * np.cos(y / (5 * PIXEL)) / (7 * PIXEL) * 1e-4,
                      -np.sin(x / (7 * PIXEL)) * np.sin(y / (5 * PIXEL)) / (5 * PIXEL) * 1e-4),
        (30, 40))
    mask = np.zeros((30, 40), dtype=bool)
    mask[3:23, 10:34] = True
    fast = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL)
    assert applications == [1]
    exact = integrate_normals(normals, mask=mask, pixel_size_m=PIXEL,
                              method=IntegrationMethod.EXACT)
    # float32 (2^-24 = 6e-8 per rounding, a few of them in the transforms and the column
    # recurrence, relative to the span) against float64: measured 3.7e-8 of the span
    assert np.abs(fast[mask] - exact[mask]).max() < 1e-6 * np.ptp(exact[mask])
