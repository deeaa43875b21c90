"""Tests of fingerps_calib.lights.sphere_calibration on analytic inputs.

Silhouettes are computed exactly (the tangent cone of the sphere, or pixel coverage of
the ray-sphere hit test), highlights are Gaussian blobs put at the projection of chosen
surface points, whose mirror directions are known in closed form (Eq. 10).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.sphere_calibration import calibrate_lights, calibrate_lights_orthographic
from fingerps_calib.lights.sphere_highlight import highlight_centroid, light_direction
from fingerps_calib.lights.sphere_silhouette import fit_sphere_center, sphere_edge_points

H, W = 240, 320
K = np.array([[400.0, 0.0, 161.3], [0.0, 402.0, 118.7], [0.0, 0.0, 1.0]])
CENTER = np.array([0.006, -0.004, 0.07])
RADIUS = 0.008


def _project(points: np.ndarray) -> np.ndarray:
    p = points @ K.T
    return p[:, :2] / p[:, 2:]


def _silhouette_points(center: np.ndarray, radius: float, n: int) -> np.ndarray:
    """Exact projection of the sphere's tangent cone (the silhouette), (n, 2) pixels."""
    axis = center / np.linalg.norm(center)
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    alpha = np.arcsin(radius / np.linalg.norm(center))
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)[:, None]
    rays = np.cos(alpha) * axis + np.sin(alpha) * (np.cos(t) * e1 + np.sin(t) * e2)
    return _project(rays)


def _coverage(center: np.ndarray, radius: float, supersample: int = 4) -> np.ndarray:
    """Fraction of each pixel whose rays hit the sphere, (H, W) float64."""
    ss = supersample
    vv, uu = np.mgrid[0 : H * ss, 0 : W * ss]
    u, v = (uu + 0.5) / ss - 0.5, (vv + 0.5) / ss - 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    along = d @ center
    hit = along**2 - center @ center + radius**2 >= 0
    return hit.reshape(H, ss, W, ss).mean(axis=(1, 3))


def _blob(u0: float, v0: float, sigma: float, amplitude: float) -> np.ndarray:
    vv, uu = np.mgrid[0:H, 0:W]
    return amplitude * np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * sigma**2))


def _mirror(normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Eq. 10 forward: direction towards the light seen in the mirror at ``point``."""
    r = -point / np.linalg.norm(point)
    return 2 * (normal @ r) * normal - r


def _sphere_images(normals: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(K, H, W) uint8 sphere images with highlights at the given surface normals."""
    coverage = _coverage(CENTER, RADIUS)
    points = CENTER + RADIUS * normals
    uv = _project(points)
    images = []
    for u, v in uv:
        image = 40.0 * coverage + 4.0 + _blob(u, v, 1.5, 600.0) * coverage
        images.append(np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255))
    truth = np.array([_mirror(n, p) for n, p in zip(normals, points, strict=True)])
    return np.round(images).astype(np.uint8), uv, truth


def _facing_normals(count: int) -> np.ndarray:
    """Normals tilted 8..20 degrees from the direction towards the camera."""
    towards = -CENTER / np.linalg.norm(CENTER)
    e1 = np.cross(towards, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(towards, e1)
    az = np.linspace(0, 2 * np.pi, count, endpoint=False)
    tilt = np.deg2rad(np.linspace(8, 20, count))[:, None]
    n = np.cos(tilt) * towards + np.sin(tilt) * (
        np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2
    )
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_fit_sphere_center_on_exact_silhouette():
    edges = _silhouette_points(CENTER, RADIUS, 400)
    fit = fit_sphere_center(edges, camera_matrix=K, radius_m=RADIUS)
    assert fit.converged
    np.testing.assert_allclose(fit.center_optical_m, CENTER, atol=1e-9)
    assert fit.rms_residual_px < 1e-6
    assert fit.residuals_px.shape == (400,)


def test_fit_sphere_center_residual_is_in_pixels():
    # Noise of 0.3 px normal to the silhouette gives an rms residual of about 0.3 px.
    rng = np.random.default_rng(1)
    edges = _silhouette_points(CENTER, RADIUS, 2000)
    centre_uv = edges.mean(axis=0)
    outward = (edges - centre_uv) / np.linalg.norm(edges - centre_uv, axis=1, keepdims=True)
    noisy = edges + outward * rng.normal(0, 0.3, (len(edges), 1))
    fit = fit_sphere_center(noisy, camera_matrix=K, radius_m=RADIUS)
    assert fit.rms_residual_px == pytest.approx(0.3, rel=0.1)
    assert np.linalg.norm(fit.center_optical_m - CENTER) < 1e-4
    # A wrong radius scales the distance, not the silhouette: same residual, centre * 1.1.
    fit_big = fit_sphere_center(noisy, camera_matrix=K, radius_m=1.1 * RADIUS)
    np.testing.assert_allclose(fit_big.center_optical_m, 1.1 * fit.center_optical_m,
                               rtol=1e-5)


def test_fit_sphere_center_rejects_bad_input():
    with pytest.raises(FingerpsCalibError, match=r"\(N, 2\)"):
        fit_sphere_center(np.zeros((3, 2)), camera_matrix=K, radius_m=RADIUS)
    with pytest.raises(FingerpsCalibError, match=r"radius"):
        fit_sphere_center(_silhouette_points(CENTER, RADIUS, 50), camera_matrix=K,
                          radius_m=0.0)
    with pytest.raises(FingerpsCalibError, match=r"camera_matrix"):
        fit_sphere_center(_silhouette_points(CENTER, RADIUS, 50), camera_matrix=np.eye(2),
                          radius_m=RADIUS)


def test_edge_points_lie_on_the_true_silhouette():
    rng = np.random.default_rng(2)
    coverage = _coverage(CENTER, RADIUS)
    image = 50.0 * coverage + 3.0 + rng.normal(0, 0.5, coverage.shape)
    edges = sphere_edge_points(image.astype(np.float32))
    # Angle between each edge point's ray and the tangent cone, in pixels at the focal length.
    rays = np.column_stack([edges, np.ones(len(edges))]) @ np.linalg.inv(K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    axis = CENTER / np.linalg.norm(CENTER)
    beta = np.arccos(rays @ axis)
    error_px = (beta - np.arcsin(RADIUS / np.linalg.norm(CENTER))) * K[0, 0]
    outline_px = 2 * np.pi * K[0, 0] * np.tan(np.arcsin(RADIUS / np.linalg.norm(CENTER)))
    assert len(edges) > 0.9 * outline_px  # about one point per pixel of outline
    # Unbiased on a sharp step; the scatter (~0.08 px) is the pixel-phase dependence of
    # interpolating a one-pixel-wide edge, which averages out in the fit.
    assert abs(np.mean(error_px)) < 0.03
    assert np.sqrt(np.mean(error_px**2)) < 0.12
    assert np.abs(error_px).max() < 0.35
    fit = fit_sphere_center(edges, camera_matrix=K, radius_m=RADIUS)
    assert fit.rms_residual_px < 0.12
    assert np.linalg.norm(fit.center_optical_m - CENTER) < 0.03e-3


def test_edge_points_from_a_mask():
    coverage = _coverage(CENTER, RADIUS)
    edges = sphere_edge_points(np.zeros((2, H, W)), mask=coverage >= 0.5)
    fit = fit_sphere_center(edges, camera_matrix=K, radius_m=RADIUS)
    assert fit.rms_residual_px < 0.3  # a binary mask is only good to about a pixel
    assert np.linalg.norm(fit.center_optical_m - CENTER) < 0.2e-3
    with pytest.raises(FingerpsCalibError, match=r"mask"):
        sphere_edge_points(np.zeros((2, H, W)), mask=np.ones((H, W + 1), bool))


def test_edge_points_of_a_black_image_are_empty():
    assert sphere_edge_points(np.zeros((3, H, W), np.uint8)).shape == (0, 2)


def test_highlight_centroid_subpixel_saturated_and_second_reflection():
    rng = np.random.default_rng(3)
    u0, v0 = 150.37, 112.81
    image = 30.0 + _blob(u0, v0, 2.0, 900.0)  # saturates a plateau of ~3 px radius
    image += _blob(175.0, 100.0, 1.5, 200.0)  # a second, weaker reflection
    image += 20.0 * np.linspace(0, 1, W)[None, :]  # diffuse shading
    image = np.clip(image + rng.normal(0, 1.0, image.shape), 0, 255).astype(np.uint8)
    assert (image == 255).sum() > 20
    u, v = highlight_centroid(image, disc_center_uv=(160.0, 120.0), disc_radius_px=50.0)
    assert np.hypot(u - u0, v - v0) < 0.05


def test_highlight_centroid_only_searches_the_disc():
    image = 10.0 + _blob(100.0, 100.0, 1.5, 200.0) + _blob(20.0, 20.0, 1.5, 250.0)
    u, v = highlight_centroid(image, disc_center_uv=(100.0, 100.0), disc_radius_px=30.0)
    assert np.hypot(u - 100.0, v - 100.0) < 0.01
    with pytest.raises(FingerpsCalibError, match=r"no highlight"):
        highlight_centroid(np.full((H, W), 7.0), disc_center_uv=(100.0, 100.0),
                           disc_radius_px=30.0)


def test_light_direction_inverts_the_mirror_reflection():
    normals = _facing_normals(7)
    points = CENTER + RADIUS * normals
    for normal, point, uv in zip(normals, points, _project(points), strict=True):
        got = light_direction(uv, sphere_center=CENTER, radius_m=RADIUS, camera_matrix=K)
        np.testing.assert_allclose(got, _mirror(normal, point), atol=1e-10)
        assert got[2] < 0  # towards the camera side
    # The point whose normal looks at the camera reflects the light back along the ray.
    centre_uv = _project(CENTER[None, :] - RADIUS * CENTER / np.linalg.norm(CENTER))[0]
    got = light_direction(centre_uv, sphere_center=CENTER, radius_m=RADIUS, camera_matrix=K)
    np.testing.assert_allclose(got, -CENTER / np.linalg.norm(CENTER), atol=1e-10)
    with pytest.raises(FingerpsCalibError, match=r"misses the sphere"):
        light_direction(np.array([1.0, 1.0]), sphere_center=CENTER, radius_m=RADIUS,
                        camera_matrix=K)


def test_calibrate_lights_recovers_directions():
    rng = np.random.default_rng(4)
    normals = _facing_normals(7)
    images, uv, truth = _sphere_images(normals, rng)
    result = calibrate_lights(images, camera_matrix=K, radius_m=RADIUS)
    assert result.ok, result.problems
    assert result.problems == ()
    np.testing.assert_allclose(result.highlights_uv, uv, atol=0.1)
    angles = np.degrees(np.arccos(np.clip(np.sum(result.directions_optical * truth, 1), -1, 1)))
    assert angles.max() < 0.3, angles
    assert np.linalg.norm(result.sphere_center_optical_m - CENTER) < 0.1e-3
    assert result.edge_rms_px < 0.2
    assert np.all(result.residuals_px < 0.3)
    np.testing.assert_allclose(result.directions_ps[:, 1:], -result.directions_optical[:, 1:])


def test_calibrate_lights_undistorts_points():
    rng = np.random.default_rng(6)
    images, uv, truth = _sphere_images(_facing_normals(4), rng)
    distortion = np.array([-0.25, 0.1, 0.001, -0.002, 0.0])
    # Distorted image: the pixel at distorted (u, v) shows the ideal image at its
    # undistorted position.
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
    ideal = cv2.undistortPoints(np.stack([uu, vv], -1).reshape(-1, 1, 2), K, distortion, P=K)
    map_u, map_v = ideal.reshape(H, W, 2).transpose(2, 0, 1)
    distorted = np.stack([
        cv2.remap(image, map_u, map_v, cv2.INTER_LINEAR, borderValue=4) for image in images
    ])
    result = calibrate_lights(distorted, camera_matrix=K, radius_m=RADIUS,
                              distortion=distortion)
    assert result.ok, result.problems
    np.testing.assert_allclose(result.highlights_uv, uv, atol=0.15)
    angles = np.degrees(np.arccos(np.clip(np.sum(result.directions_optical * truth, 1), -1, 1)))
    assert angles.max() < 0.4, angles
    assert np.linalg.norm(result.sphere_center_optical_m - CENTER) < 0.15e-3
    ignored = calibrate_lights(distorted, camera_matrix=K, radius_m=RADIUS)
    assert np.linalg.norm(ignored.sphere_center_optical_m - CENTER) > 0.5e-3


def test_calibrate_lights_reports_failures_instead_of_bad_results():
    rng = np.random.default_rng(5)
    images, _, _ = _sphere_images(_facing_normals(3), rng)
    dark = images.copy()
    dark[1] = np.where(_coverage(CENTER, RADIUS) > 0, 44, 4).astype(np.uint8)  # LED 1 off
    result = calibrate_lights(dark, camera_matrix=K, radius_m=RADIUS)
    assert not result.ok
    assert any(p.startswith("LED 1:") for p in result.problems), result.problems
    assert np.all(np.isnan(result.directions_optical[1]))
    assert np.all(np.isfinite(result.directions_optical[[0, 2]]))

    black = calibrate_lights(np.zeros((3, H, W), np.uint8), camera_matrix=K,
                             radius_m=RADIUS)
    assert not black.ok and "sphere not found" in black.problems[0]
    assert np.all(np.isnan(black.directions_optical))

    wrong_k = K.copy()
    wrong_k[0, 0] *= 1.3  # the silhouette no longer fits a sphere's outline
    bad = calibrate_lights(images, camera_matrix=wrong_k, radius_m=RADIUS)
    assert not bad.ok and any("rms" in p for p in bad.problems), bad.problems


def test_calibrate_lights_rejects_bad_shapes():
    with pytest.raises(FingerpsCalibError, match=r"\(K, H, W\)"):
        calibrate_lights(np.zeros((H, W)), camera_matrix=K, radius_m=RADIUS)
    with pytest.raises(FingerpsCalibError, match=r"camera_matrix"):
        calibrate_lights(np.zeros((2, H, W)), camera_matrix=np.eye(4), radius_m=RADIUS)
    with pytest.raises(FingerpsCalibError, match=r"radius"):
        calibrate_lights(np.zeros((2, H, W)), camera_matrix=K, radius_m=-1.0)


def test_orthographic_fallback():
    # Orthographic chrome sphere: disc of radius 60 px; highlight at normal n shows light
    # 2 (n.v) n - v with v = (0, 0, 1) in the PS frame.
    rho, cu, cv = 60.0, 158.4, 121.2
    vv, uu = np.mgrid[0:H, 0:W]
    disc = np.clip(rho - np.hypot(uu - cu, vv - cv) + 0.5, 0, 1)
    lights = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86], [0.0, -0.6, 0.8]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    normals = lights + np.array([0.0, 0.0, 1.0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    images = np.stack([
        30 * disc + _blob(cu + rho * n[0], cv - rho * n[1], 1.5, 200.0) for n in normals
    ])
    result = calibrate_lights_orthographic(images)
    assert result.ok, result.problems
    np.testing.assert_allclose(result.directions_ps, lights, atol=5e-3)
    assert result.circle_radius_px == pytest.approx(rho, abs=0.1)
