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


# ----------------------------------------------------------------- per-pixel (near) lights

#: Seven LED positions around the camera (PS frame, metres), as on the rig: a ring of
#: radius 40 mm in the lens plane, the object 90 mm in front (z = -0.09 in the PS frame).
_LED_RING_M = np.array(
    [[0.04 * np.cos(a), 0.04 * np.sin(a), 0.0] for a in np.radians(np.arange(7) * 360 / 7 + 8)]
)


def _near_lights(size: int = 81) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normals, mask, per-pixel unit light directions (K, H, W, 3) and the inverse-square
    irradiance (K, H, W) of an 8 mm sphere whose pixels are 0.2 mm apart, 90 mm away."""
    normals, mask = _sphere(size)
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    r = (size - 1) / 2 - 0.5
    scale = 4e-3 / r  # metres per pixel
    x = (u - (size - 1) / 2) * scale
    y = -(v - (size - 1) / 2) * scale
    points = np.stack([x, y, -0.09 + 4e-3 * normals[..., 2]], axis=-1)
    to_led = _LED_RING_M[:, None, None, :] - points[None]
    dist = np.linalg.norm(to_led, axis=-1)
    return normals, mask, to_led / dist[..., None], (0.09 / dist) ** 2


def test_per_pixel_lights_recover_a_near_lit_sphere() -> None:
    normals, mask, lights, irradiance = _near_lights()
    rng = np.random.default_rng(3)
    rho = rng.uniform(0.3, 0.9, size=mask.shape)
    images = (irradiance * lambertian_shading(normals, lights, rho=rho)).astype(np.float32)
    lit = (np.einsum("hwc,khwc->khw", normals, lights) > 0).sum(axis=0)
    for lights_in, intensities in (
        (lights, irradiance),  # direction and irradiance per pixel
        (lights * irradiance[..., None], None),  # irradiance folded into the light vectors
    ):
        res = solve_lambertian(images, lights_in, intensities=intensities, mask=mask)
        np.testing.assert_array_equal(res.used_lights[mask], lit[mask])
        np.testing.assert_array_equal(res.valid, mask & (lit >= 3))
        assert (res.valid & (lit < 7)).sum() > 50  # attached shadows were left out
        assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.05
        np.testing.assert_allclose(res.albedo[res.valid], rho[res.valid], rtol=1e-4)
        np.testing.assert_allclose(np.linalg.norm(res.normals[res.valid], axis=-1), 1, rtol=1e-6)
    # The distant-light approximation (directions from the centre) is degrees off here.
    centre = lights[:, 40, 40]
    distant = solve_lambertian(images, centre, intensities=irradiance[:, 40, 40], mask=mask)
    assert np.nanmean(angular_error_deg(distant.normals, normals, mask=distant.valid)) > 1.0


def test_per_pixel_lights_match_the_distant_solver() -> None:
    normals, mask = _sphere()
    rho = np.random.default_rng(4).uniform(0.3, 0.9, size=mask.shape)
    e = np.array([1.0, 0.5, 2.0, 1.3, 0.8, 1.1, 0.6])
    images = _render(normals, rho, LIGHTS) * e[:, None, None]
    images[1][:, :40] = 0.01  # a cast shadow
    kwargs = {"mask": mask, "shadow_level": 0.02, "saturation_level": 1.5}
    distant = solve_lambertian(images, LIGHTS, intensities=e, **kwargs)
    per_pixel = solve_lambertian(
        images, np.broadcast_to(LIGHTS[:, None, None, :], (7, *mask.shape, 3)),
        intensities=e, **kwargs,
    )
    intensity_maps = solve_lambertian(
        images, LIGHTS, intensities=np.broadcast_to(e[:, None, None], images.shape), **kwargs
    )
    for res in (per_pixel, intensity_maps):
        np.testing.assert_array_equal(res.valid, distant.valid)
        np.testing.assert_array_equal(res.used_lights, distant.used_lights)
        np.testing.assert_allclose(res.normals, distant.normals, atol=2e-6)
        np.testing.assert_allclose(res.albedo, distant.albedo, rtol=2e-5)


def test_per_pixel_unusable_lights_are_left_out() -> None:
    normals = np.zeros((1, 4, 3))
    normals[..., 2] = 1.0
    lights = np.broadcast_to(LIGHTS[:, None, None, :], (7, 1, 4, 3)).copy()
    images = _render(normals, 0.5, LIGHTS)
    lights[2, 0, 0] = np.nan  # pixel 0: a light without a direction there
    intensities = np.ones((7, 1, 4))
    intensities[3, 0, 1] = np.nan  # pixel 1: one without an intensity ...
    intensities[4, 0, 1] = 0.0  # ... and one without light
    images[:4, 0, 2] = 0.0  # pixel 2: only 3 lights see it ...
    lights[4, 0, 2] = np.inf  # ... and one of them has no direction: 2 left
    res = solve_lambertian(images, lights, intensities=intensities)
    np.testing.assert_array_equal(res.used_lights[0], [6, 5, 2, 7])
    np.testing.assert_array_equal(res.valid[0], [True, True, False, True])
    np.testing.assert_allclose(res.normals[0, [0, 1, 3]], [[0, 0, 1]] * 3, atol=1e-6)
    np.testing.assert_allclose(res.albedo[0, [0, 1, 3]], 0.5, rtol=1e-5)
    assert np.all(res.normals[0, 2] == 0) and res.albedo[0, 2] == 0


def test_per_pixel_coplanar_lights_are_invalid() -> None:
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [-0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    n = np.array([[[0.1, 0.2, 0.97]]]) / np.linalg.norm([0.1, 0.2, 0.97])
    images = _render(n, 1.0, lights)
    per_pixel = lights[:, None, None, :]
    assert solve_lambertian(images, per_pixel).valid[0, 0]
    images[3] = 0.0  # the three left all lie in the x-z plane
    res = solve_lambertian(images, per_pixel)
    assert res.used_lights[0, 0] == 3 and not res.valid[0, 0]


def test_float32_thresholds_are_exact() -> None:
    # float32(0.1) is a little above 0.1: a value equal to it is above a shadow level of 0.1
    # (and not below a saturation level of 0.1), whatever the images' dtype.
    normals, mask = _sphere(21)
    images = _render(normals, 1.0, LIGHTS).astype(np.float32)
    images[0][mask] = np.float32(0.1)
    exact = images[:, mask].astype(np.float64)  # compared as real numbers
    for imgs in (images, images.astype(np.float64)):
        above = solve_lambertian(imgs, LIGHTS, mask=mask, shadow_level=0.1)
        below = solve_lambertian(imgs, LIGHTS, mask=mask, saturation_level=0.1)
        np.testing.assert_array_equal(above.used_lights[mask], (exact > 0.1).sum(axis=0))
        np.testing.assert_array_equal(
            below.used_lights[mask], ((exact > 0) & (exact < 0.1)).sum(axis=0)
        )
    # A comparison in float32 would count light 0 the other way at every pixel.
    assert np.all((images[0][mask] > np.float32(0.1)) != (exact[0] > 0.1))


def test_more_than_eight_lights() -> None:
    ring = [
        [np.cos(a) * np.sin(np.radians(40)), np.sin(a) * np.sin(np.radians(40)),
         np.cos(np.radians(40))]
        for a in np.radians(np.arange(0, 360, 36))
    ]
    lights = np.array([[0.0, 0.0, 1.0], *ring])  # 11 lights: 64-bit light patterns
    normals, mask = _sphere()
    images = _render(normals, 0.7, lights)
    res = solve_lambertian(images, lights, mask=mask)
    lit = (np.einsum("hwc,kc->khw", normals, lights) > 0).sum(axis=0)
    np.testing.assert_array_equal(res.used_lights[mask], lit[mask])
    assert (res.valid & (lit < 11)).sum() > 50
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.1


@pytest.mark.parametrize(
    ("lights_shape", "intensities_shape", "match"),
    [
        ((7, 5, 5, 2), None, "lights must have shape"),
        ((7, 5, 6, 3), None, "lights must have shape"),
        ((7, 3), (7, 5, 6), "intensities"),
        ((7, 5, 5, 3), (7, 5), "intensities"),
    ],
)
def test_per_pixel_bad_shapes_raise(
    lights_shape: tuple[int, ...], intensities_shape: tuple[int, ...] | None, match: str
) -> None:
    lights = np.zeros(lights_shape)
    lights[..., -1] = 1.0
    intensities = None if intensities_shape is None else np.ones(intensities_shape)
    with pytest.raises(FingerpsReconError, match=match):
        solve_lambertian(np.ones((7, 5, 5)), lights, intensities=intensities)
