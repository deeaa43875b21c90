"""Any number of lights >= 3: 96 lights, as every DiLiGenT object, in both reflectance models.

A sphere cap rendered under 96 distant lights in a DiLiGenT-like cone (5-40 degrees from the
camera axis, the attached shadows left out) is solved by the Lambertian solver (distant and
per-pixel lights, Lambertian data) and by the HK solver (HK data with its
scale A), each recovering the known normals; more than 64 lights, so no per-pixel light
pattern may be held in a 64-bit mask.
"""

from __future__ import annotations

import numpy as np
import pytest
from analytic_surfaces import sphere_normals

from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.hk_model import hk_reflectance
from fingerps_recon.photometric.hk_solver import solve_hk
from fingerps_recon.photometric.lambertian import lambertian_shading, solve_lambertian

K = 96
SCALE = 45.0  # the HK model's A, as on the rig


def _lights(count: int = K) -> np.ndarray:
    """Unit directions (count, 3), PS frame, 5-40 degrees from the camera axis."""
    rng = np.random.default_rng(96)
    azimuth = rng.uniform(0.0, 2.0 * np.pi, count)
    tilt = np.radians(rng.uniform(5.0, 40.0, count))
    return np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                     np.cos(tilt)], axis=1)


def _cap(size: int = 51) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) of a sphere cap out to 72 degrees (PS frame) and its mask."""
    normals, mask, _ = sphere_normals(size, size, radius_px=(size - 1) / 2 - 0.5, within=0.9)
    return normals, mask


def test_lambertian_with_96_lights_distant_and_per_pixel() -> None:
    lights = _lights()
    normals, mask = _cap()
    rng = np.random.default_rng(1)
    rho = rng.uniform(0.3, 0.9, mask.shape)
    e = rng.uniform(0.7, 1.3, K)
    images = (lambertian_shading(normals, lights[:, None, None, :], rho=rho)
              * e[:, None, None]).astype(np.float32)
    lit = (np.einsum("hwc,kc->khw", normals, lights) > 0).sum(axis=0)
    assert lit[mask].min() < K  # attached shadows at the rim, left out
    per_pixel = np.ascontiguousarray(
        np.broadcast_to(lights[:, None, None, :], (K, *mask.shape, 3)), dtype=np.float32)
    for lgt in (lights, per_pixel):
        res = solve_lambertian(images, lgt, intensities=e, mask=mask)
        np.testing.assert_array_equal(res.valid, mask)
        np.testing.assert_array_equal(res.used_lights[mask], lit[mask])
        assert np.nanmax(angular_error_deg(res.normals, normals, mask=mask)) < 0.01
        np.testing.assert_allclose(res.albedo[mask], rho[mask], rtol=1e-4)
        assert res.relative_misfit() < 1e-5


def test_hk_with_96_lights() -> None:
    lights = _lights()
    normals, mask = _cap()
    rho = np.random.default_rng(2).uniform(0.4, 0.6, mask.shape)
    images = hk_reflectance(normals, lights[:, None, None, :], np.array([0.0, 0.0, 1.0]),
                            rho=rho, scale=SCALE) * mask
    lam = solve_lambertian(images, lights, mask=mask)
    assert lam.valid.sum() == mask.sum()
    # The Lambertian start is biased by the single-scattering term ...
    assert np.nanmean(angular_error_deg(lam.normals, normals, mask=mask)) > 1.0
    res = solve_hk(images, lights, mask=lam.valid, init_normals=lam.normals,
                   init_albedo=lam.albedo, iterations=40)
    # ... which the HK solver removes, with all 96 lights.
    np.testing.assert_array_equal(res.valid, mask)
    assert np.nanmax(angular_error_deg(res.normals, normals, mask=mask)) < 0.01
    assert res.scale == pytest.approx(SCALE, rel=1e-3)
    np.testing.assert_allclose(res.albedo[mask], rho[mask], rtol=1e-3)
