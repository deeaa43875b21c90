"""Tests of fingerps_recon.lambertian on rendered spheres."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.angular_error import angular_error_deg
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.lambertian import LambertianResult, lambertian_shading, solve_lambertian

# Seven lights around the camera, as on the rig: one central, six on a ring (PS frame).
_RING = [
    [np.cos(a) * np.sin(np.radians(35)), np.sin(a) * np.sin(np.radians(35)), np.cos(np.radians(35))]
    for a in np.radians(np.arange(0, 360, 60))
]
LIGHTS = np.array([[0.0, 0.0, 1.0], *_RING])


def _sphere(size: int = 81) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) of an orthographic sphere (PS frame, y up) and its mask."""
    r = (size - 1) / 2 - 0.5
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x = (u - (size - 1) / 2) / r
    y = -(v - (size - 1) / 2) / r
    mask = x**2 + y**2 < 1
    z = np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    normals = np.where(mask[..., None], np.stack([x, y, z], axis=-1), 0.0)
    return normals, mask


def _render(normals: np.ndarray, rho: np.ndarray | float, lights: np.ndarray) -> np.ndarray:
    return lambertian_shading(normals, lights[:, None, None, :], rho=rho)


def test_shading_is_clamped_cosine_and_broadcasts() -> None:
    normals, _ = _sphere(21)
    images = _render(normals, 0.7, LIGHTS)
    assert images.shape == (7, 21, 21)
    expected = 0.7 * np.maximum(np.einsum("hwc,kc->khw", normals, LIGHTS), 0)
    np.testing.assert_allclose(images, expected, rtol=1e-14)
    f32 = lambertian_shading(normals.astype(np.float32), LIGHTS[0].astype(np.float32), rho=0.7)
    assert f32.dtype == np.float32


def test_sphere_recovered_noise_free_including_attached_shadows() -> None:
    normals, mask = _sphere()
    rng = np.random.default_rng(0)
    rho = rng.uniform(0.3, 0.9, size=mask.shape)
    images = _render(normals, rho, LIGHTS).astype(np.float32)
    res = solve_lambertian(images, LIGHTS, mask=mask)
    assert isinstance(res, LambertianResult)
    assert res.normals.dtype == np.float32 and res.albedo.dtype == np.float32
    assert res.valid.dtype == bool and res.used_lights.dtype == np.uint8
    lit = (np.einsum("hwc,kc->khw", normals, LIGHTS) > 0).sum(axis=0)
    np.testing.assert_array_equal(res.used_lights[mask], lit[mask])
    np.testing.assert_array_equal(res.valid, mask & (lit >= 3))
    # The rim has lights in attached shadow: those must have been left out, not fitted as 0.
    partly_shadowed = res.valid & (lit < 7)
    assert partly_shadowed.sum() > 50
    err = angular_error_deg(res.normals, normals, mask=res.valid)
    assert np.nanmax(err) < 0.1
    np.testing.assert_allclose(res.albedo[res.valid], rho[res.valid], rtol=1e-4)
    assert np.all(res.normals[~res.valid] == 0) and np.all(res.albedo[~res.valid] == 0)
    np.testing.assert_allclose(np.linalg.norm(res.normals[res.valid], axis=-1), 1, rtol=1e-6)


def test_saturated_values_are_left_out() -> None:
    normals, mask = _sphere()
    images = _render(normals, 1.0, LIGHTS)
    level = 0.9
    clipped = np.minimum(images, level)
    assert np.any(clipped[:, mask] >= level)
    res = solve_lambertian(clipped, LIGHTS, mask=mask, saturation_level=level)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.1
    # Without the saturation test the clipped values bias the normals.
    biased = solve_lambertian(clipped, LIGHTS, mask=mask)
    assert np.nanmax(angular_error_deg(biased.normals, normals, mask=biased.valid)) > 1.0
    assert np.all(res.used_lights[mask] <= biased.used_lights[mask])


def test_shadow_level_excludes_dim_values() -> None:
    normals, mask = _sphere()
    # A cast shadow: light 1 blocked over the left half, leaving a small ambient value.
    images = _render(normals, 1.0, LIGHTS)
    shadow = np.zeros(mask.shape, dtype=bool)
    shadow[:, :40] = True
    images[1][shadow] = 0.01
    res = solve_lambertian(images, LIGHTS, mask=mask, shadow_level=0.02)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.1
    naive = solve_lambertian(images, LIGHTS, mask=mask, shadow_level=0.0)
    assert np.nanmax(angular_error_deg(naive.normals, normals, mask=naive.valid)) > 1.0


def test_fewer_than_three_usable_lights_is_invalid() -> None:
    normals = np.array([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])  # (1, 2, 3)
    images = _render(normals, 1.0, LIGHTS)
    images[2:, 0, 0] = 0.0  # pixel (0, 0): only lights 0 and 1 see it
    res = solve_lambertian(images, LIGHTS)
    assert not res.valid[0, 0] and res.used_lights[0, 0] == 2
    assert np.all(res.normals[0, 0] == 0) and res.albedo[0, 0] == 0
    assert res.valid[0, 1] and res.used_lights[0, 1] == 7


def test_coplanar_lights_are_invalid_not_guessed() -> None:
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [-0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    n = np.array([[[0.1, 0.2, 0.97]]]) / np.linalg.norm([0.1, 0.2, 0.97])
    images = _render(n, 1.0, lights)
    assert solve_lambertian(images, lights).valid[0, 0]
    images[3] = 0.0  # the three left all lie in the x-z plane
    res = solve_lambertian(images, lights)
    assert res.used_lights[0, 0] == 3 and not res.valid[0, 0]


def test_light_intensities_are_honoured() -> None:
    normals, mask = _sphere(41)
    e = np.array([1.0, 0.5, 2.0, 1.3, 0.8, 1.1, 0.6])
    images = _render(normals, 0.6, LIGHTS) * e[:, None, None]
    res = solve_lambertian(images, LIGHTS, intensities=e, mask=mask)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.1
    np.testing.assert_allclose(res.albedo[res.valid], 0.6, rtol=1e-5)
    ignored = solve_lambertian(images, LIGHTS, mask=mask)
    assert np.nanmax(angular_error_deg(ignored.normals, normals, mask=ignored.valid)) > 1.0


def test_mask_and_input_untouched() -> None:
    normals, mask = _sphere(41)
    images = _render(normals, 0.5, LIGHTS)
    before = images.copy()
    sub = mask.copy()
    sub[:20] = False
    res = solve_lambertian(images, LIGHTS, mask=sub)
    np.testing.assert_array_equal(images, before)
    assert not res.valid[:20].any() and res.valid[20:].any()
    assert np.all(res.used_lights[:20] == 0)


def test_integer_images_are_accepted() -> None:
    normals, mask = _sphere(41)
    images = np.round(_render(normals, 200.0, LIGHTS)).astype(np.uint8)
    res = solve_lambertian(images, LIGHTS, mask=mask, saturation_level=255)
    # 8-bit quantisation: a few degrees at most where the signal is weak.
    assert np.nanmedian(angular_error_deg(res.normals, normals, mask=res.valid)) < 1.0


@pytest.mark.parametrize(
    ("images_shape", "lights_shape", "kwargs", "match"),
    [
        ((7, 5), (7, 3), {}, "images must have shape"),
        ((7, 5, 5), (6, 3), {}, "lights must have shape"),
        ((7, 5, 5), (7, 2), {}, "lights must have shape"),
        ((2, 5, 5), (2, 3), {}, "at least 3 lights"),
        ((7, 5, 5), (7, 3), {"intensities": np.ones(6)}, "intensities"),
        ((7, 5, 5), (7, 3), {"intensities": -np.ones(7)}, "intensities"),
        ((7, 5, 5), (7, 3), {"mask": np.ones((5, 4), bool)}, "mask"),
    ],
)
def test_bad_shapes_raise(
    images_shape: tuple[int, ...], lights_shape: tuple[int, ...], kwargs: dict, match: str
) -> None:
    lights = np.zeros(lights_shape)
    if lights_shape[-1] == 3:
        lights[:, 2] = 1.0
    with pytest.raises(FingerpsReconError, match=match):
        solve_lambertian(np.ones(images_shape), lights, **kwargs)
