"""Tests of fingerps_recon.photometric.lambertian on rendered spheres."""

from __future__ import annotations

import numpy as np
import pytest
from analytic_surfaces import sphere_normals

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric import kernel_threads
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.lambertian import (
    LambertianResult,
    LightRows,
    lambertian_shading,
    light_rows,
    solve_lambertian,
)

# Seven lights around the camera, as on the rig: one central, six on a ring (PS frame).
_RING = [
    [np.cos(a) * np.sin(np.radians(35)), np.sin(a) * np.sin(np.radians(35)), np.cos(np.radians(35))]
    for a in np.radians(np.arange(0, 360, 60))
]
LIGHTS = np.array([[0.0, 0.0, 1.0], *_RING])

#: float32's unit roundoff (half its eps).
U32 = float(np.finfo(np.float32).eps) / 2


def _float32_solve_tol(cond_lights: float) -> float:
    """What a float32 least-squares solve resolves of b = rho n, relative to |b|: its 3x3
    normal equations A = L^T L (sums over the lights, then the adjugate) lose a few roundings
    times cond(A) = cond(L)^2; 4 of them (measured at most 1.3 on these spheres)."""
    return 4 * cond_lights**2 * U32


def _worst_cond(lights: np.ndarray, usable: np.ndarray, where: np.ndarray) -> float:
    """Largest condition number of the (K, 3) ``lights`` over the sets of lights ``usable``
    (K, H, W) at the pixels ``where``."""
    patterns = np.unique(usable[:, where].T, axis=0)
    return max(float(np.linalg.cond(lights[used])) for used in patterns)


def _sphere(size: int = 81) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) of an orthographic sphere filling a size x size image, and its mask."""
    normals, mask, _ = sphere_normals(size, size, radius_px=(size - 1) / 2 - 0.5)
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


@pytest.mark.parametrize("per_pixel", [False, True], ids=["distant", "per_pixel"])
def test_coplanar_lights_are_invalid_not_guessed(per_pixel: bool) -> None:
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [-0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    n = np.array([[[0.1, 0.2, 0.97]]]) / np.linalg.norm([0.1, 0.2, 0.97])
    images = _render(n, 1.0, lights)
    given = lights[:, None, None, :] if per_pixel else lights  # (K, 1, 1, 3) or (K, 3)
    assert solve_lambertian(images, given).valid[0, 0]
    images[3] = 0.0  # the three left all lie in the x-z plane
    res = solve_lambertian(images, given)
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
    # Each is a float32 solve of its own (the sums in another order, or the distant solver's
    # float32 pseudo-inverse), each within 1.3 cond(A) roundings of the truth (measured):
    # they agree to what float32 resolves at the worst pixel, the rim's 3 of the 7 lights
    # (cond(L) 12, cond(A) 144: 3.4e-5).
    usable = (images > 0.02) & (images < 1.5)
    tol = _float32_solve_tol(_worst_cond(LIGHTS * e[:, None], usable, distant.valid))
    for res in (per_pixel, intensity_maps):
        np.testing.assert_array_equal(res.valid, distant.valid)
        np.testing.assert_array_equal(res.used_lights, distant.used_lights)
        np.testing.assert_allclose(res.normals, distant.normals, atol=tol)
        np.testing.assert_allclose(res.albedo, distant.albedo, rtol=tol)


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
    # float32 solves; pixel 1's 5 lights are the worst conditioned (cond(L) 3.6): 3.1e-6.
    tol = _float32_solve_tol(np.linalg.cond(np.delete(LIGHTS, [3, 4], axis=0)))
    np.testing.assert_allclose(res.normals[0, [0, 1, 3]], [[0, 0, 1]] * 3, atol=tol)
    np.testing.assert_allclose(res.albedo[0, [0, 1, 3]], 0.5, rtol=1e-5)
    assert np.all(res.normals[0, 2] == 0) and res.albedo[0, 2] == 0


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


# ----------------------------------------------------------------- the compiled loop's extras


def _misfit_reference(
    images: np.ndarray, lights: np.ndarray, intensities: np.ndarray, res: LambertianResult,
    *, shadow_level: float, saturation_level: float,
) -> tuple[float, float, int]:
    """(sum of squared misfits, sum of used values, their number) over the valid pixels,
    in float64 with fancy indexing: the definition, written out."""
    rows, cols = np.nonzero(res.valid)
    value = images[:, rows, cols].astype(np.float64)
    light = lights[:, rows, cols] if lights.ndim == 4 else lights[:, None, :]
    e = intensities[:, rows, cols] if intensities.ndim == 3 else intensities[:, None]
    n = res.normals[rows, cols].astype(np.float64)
    shade = np.maximum(np.einsum("kpc,pc->kp", np.broadcast_to(light, (*value.shape, 3)), n), 0)
    predicted = e * res.albedo[rows, cols] * shade
    use = (value > shadow_level) & (value < saturation_level)
    return (float(np.sum((value - predicted)[use] ** 2)), float(value[use].sum()),
            int(use.sum()))


def test_misfit_is_the_lambertian_residual_over_the_used_values() -> None:
    # Near lights with per-pixel irradiance, 2 % noise, a cast shadow and clipped values:
    # the misfit the solve gathers is rms(I - e rho max(0, n . l)) / mean(I) over the valid
    # pixels' used values, clamp included (lit lights whose fitted n . l < 0 at the rim).
    normals, mask, lights, irradiance = _near_lights()
    rng = np.random.default_rng(5)
    rho = rng.uniform(0.3, 0.9, size=mask.shape)
    clean = irradiance * lambertian_shading(normals, lights, rho=rho)
    images = (clean * (1 + 0.02 * rng.standard_normal(clean.shape))).astype(np.float32)
    images[2][:, :30] = 0.004  # cast shadow
    levels = {"shadow_level": 0.005, "saturation_level": 0.8}
    assert np.any(images[:, mask] >= 0.8)
    res = solve_lambertian(images, lights, intensities=irradiance, mask=mask, **levels)
    sq, total, count = _misfit_reference(images, lights, irradiance, res, **levels)
    # The clamp matters at some used measurement (else this would not test it).
    fitted = np.einsum("khwc,hwc->khw", lights, res.normals)
    used = (images > 0.005) & (images < 0.8) & res.valid
    assert np.any(used & (fitted < 0))
    assert res.misfit_count == count == int(res.used_lights[res.valid].sum())
    assert res.observed_sum == pytest.approx(total, rel=1e-6)
    assert res.misfit_sq == pytest.approx(sq, rel=1e-4)
    expected = np.sqrt(sq / count) / (total / count)
    assert res.relative_misfit() == pytest.approx(expected, rel=1e-4)
    assert 0.01 < res.relative_misfit() < 0.05  # the 2 % noise

    # Noise-free data fit exactly; nothing valid gives no figure.
    exact = solve_lambertian(clean.astype(np.float32), lights, intensities=irradiance,
                             mask=mask)
    assert exact.relative_misfit() < 1e-5
    empty = solve_lambertian(images, lights, mask=np.zeros(mask.shape, bool))
    assert empty.relative_misfit() is None and empty.misfit_count == 0


def test_integer_images_are_read_as_they_are() -> None:
    # uint8 and uint16 bursts give exactly what their float32 conversion gives.
    normals, mask = _sphere(41)
    for dtype, scale in ((np.uint8, 200.0), (np.uint16, 60000.0)):
        images = np.round(_render(normals, scale, LIGHTS)).astype(dtype)
        kwargs = {"mask": mask, "shadow_level": 3, "saturation_level": scale}
        res = solve_lambertian(images, LIGHTS, **kwargs)
        ref = solve_lambertian(images.astype(np.float32), LIGHTS, **kwargs)
        assert res.valid.sum() > 0.9 * mask.sum()
        for name in ("normals", "albedo", "valid", "used_lights"):
            np.testing.assert_array_equal(getattr(res, name), getattr(ref, name), err_msg=name)
        assert res.misfit_sq == ref.misfit_sq and res.observed_sum == ref.observed_sum


def test_integer_thresholds_split_the_values_as_real_numbers() -> None:
    # Integer images are compared with float32 levels (the kernel's lanes): a fractional,
    # integral, negative or out-of-range level splits the values as the real number does.
    normals, mask = _sphere(31)
    for dtype, scale in ((np.uint8, 250.0), (np.uint16, 65000.0)):
        images = np.round(_render(normals, scale, LIGHTS)).astype(dtype)
        exact = images[:, mask].astype(np.float64)
        top = float(np.iinfo(dtype).max)
        for lo, hi in ((3.5, scale - 0.5), (3.0, scale - 1.0), (-7.2, 1e12), (-np.inf, np.inf),
                       (top + 5.0, np.inf), (20.0, -3.0), (20.0, top)):
            res = solve_lambertian(images, LIGHTS, mask=mask, shadow_level=lo,
                                   saturation_level=hi)
            expected = ((exact > lo) & (exact < hi)).sum(axis=0)
            np.testing.assert_array_equal(res.used_lights[mask], expected,
                                          err_msg=f"{dtype.__name__} {lo} {hi}")


def test_threads_do_not_change_the_result(monkeypatch: pytest.MonkeyPatch) -> None:

    normals, mask, lights, irradiance = _near_lights()
    images = (irradiance * lambertian_shading(normals, lights, rho=0.5)).astype(np.float32)
    images *= 1 + 0.01 * np.random.default_rng(6).standard_normal(images.shape).astype(
        np.float32)
    results = []
    for threads in (1, 2):
        monkeypatch.setattr(kernel_threads, "_LIMIT", [threads])
        results.append(solve_lambertian(images, lights, intensities=irradiance, mask=mask))
    one, two = results
    for name in ("normals", "albedo", "valid", "used_lights"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
    assert (one.misfit_sq, one.observed_sum) == (two.misfit_sq, two.observed_sum)


def test_lights_beyond_a_byte_count_in_uint16() -> None:
    # 300 lights: more than a uint8 can count (and than the 62 of the former bit masks).
    rng = np.random.default_rng(7)
    azimuth = rng.uniform(0, 2 * np.pi, 300)
    tilt = np.radians(rng.uniform(0, 50, 300))
    lights = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                       np.cos(tilt)], axis=1)
    normals, mask = _sphere(21)
    images = _render(normals, 0.7, lights)
    res = solve_lambertian(images, lights, mask=mask)
    lit = (np.einsum("hwc,kc->khw", normals, lights) > 0).sum(axis=0)
    assert res.used_lights.dtype == np.uint16 and lit.max() > 255
    np.testing.assert_array_equal(res.used_lights[mask], lit[mask])
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=res.valid)) < 0.1


@pytest.mark.parametrize("per_pixel", [False, True])
def test_light_rows_made_once_solve_as_the_lights_do(per_pixel: bool) -> None:
    # The pipeline makes the rows a_k = e_k l_k once per calibration (LightRows): the solve
    # from them is the solve from the lights and intensities, value for value (the same
    # float32 rows, the same sums).
    normals, mask = _sphere(41)
    e = np.array([1.0, 0.5, 2.0, 1.3, 0.8, 1.1, 0.6])
    images = (_render(normals, 0.7, LIGHTS) * e[:, None, None]).astype(np.float32)
    lights = (np.ascontiguousarray(np.broadcast_to(LIGHTS[:, None, None, :], (7, 41, 41, 3)))
              if per_pixel else LIGHTS)
    intensities = np.broadcast_to(e[:, None, None], images.shape).copy() if per_pixel else e
    rows = light_rows(lights, shape=mask.shape, intensities=intensities)
    assert isinstance(rows, LightRows) and rows.light_count == 7
    assert rows.rows.shape == ((7, 3, 41, 41) if per_pixel else (7, 3, 1, 1))
    assert not rows.rows.flags.writeable
    kwargs = {"mask": mask, "shadow_level": 0.02}
    given = solve_lambertian(images, lights, intensities=intensities, **kwargs)
    made = solve_lambertian(images, rows, **kwargs)
    np.testing.assert_array_equal(made.valid, given.valid)
    np.testing.assert_array_equal(made.used_lights, given.used_lights)
    np.testing.assert_allclose(made.normals, given.normals, atol=8 * U32)
    np.testing.assert_allclose(made.albedo, given.albedo, rtol=8 * U32)


def test_light_rows_mark_unusable_lights_and_refuse_intensities_twice() -> None:
    lights = np.broadcast_to(LIGHTS[:, None, None, :], (7, 2, 3, 3)).copy()
    intensities = np.ones((7, 2, 3))
    intensities[1, 0, 0] = 0.0
    intensities[2, 1, 2] = np.nan
    lights[3, 1, 1] = np.inf
    rows = light_rows(lights, shape=(2, 3), intensities=intensities).rows
    unusable = ~np.isfinite(rows).all(axis=1)  # (K, H, W)
    expected = np.zeros((7, 2, 3), bool)
    expected[1, 0, 0] = expected[2, 1, 2] = expected[3, 1, 1] = True
    np.testing.assert_array_equal(unusable, expected)
    made = light_rows(LIGHTS, shape=(2, 3))
    with pytest.raises(FingerpsReconError, match="give no intensities"):
        solve_lambertian(np.ones((7, 2, 3)), made, intensities=np.ones(7))
    with pytest.raises(FingerpsReconError, match="do not fit"):
        solve_lambertian(np.ones((6, 2, 3)), made)
    with pytest.raises(FingerpsReconError, match="do not fit"):
        solve_lambertian(np.ones((7, 2, 4)), light_rows(lights, shape=(2, 3)))
