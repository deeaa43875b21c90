"""Tests of fingerps_recon.photometric.hk_model on analytic cases."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import integrate

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.hk_model import (
    FINGER,
    PLASTICINE,
    PhaseConvention,
    SkinParams,
    henyey_greenstein,
    hk_reflectance,
)

Z = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize("g", [0.0, 0.5, 0.81, -0.3, 0.95])
def test_henyey_greenstein_integrates_to_one_over_the_sphere(g: float) -> None:
    # Integral over the sphere = 2 pi * integral of p over cos(theta) in [-1, 1].
    total, _ = integrate.quad(lambda c: henyey_greenstein(c, g), -1.0, 1.0, epsabs=1e-12)
    assert 2 * math.pi * total == pytest.approx(1.0, rel=1e-9)


def test_henyey_greenstein_known_values_for_skin() -> None:
    p_back, p_fwd = henyey_greenstein(np.array([-1.0, 1.0]), 0.81)
    # Closed forms: (1 - g)/(1 + g)^2 / 4 pi and (1 + g)/(1 - g)^2 / 4 pi (NOTES §1).
    assert p_back == pytest.approx(0.19 / 1.81**2 / (4 * math.pi), rel=1e-12)
    assert p_fwd == pytest.approx(1.81 / 0.19**2 / (4 * math.pi), rel=1e-12)
    assert p_back == pytest.approx(0.005, abs=0.0005)
    assert p_fwd == pytest.approx(4.0, abs=0.02)
    assert p_fwd / p_back == pytest.approx(865, rel=1e-3)


def test_henyey_greenstein_isotropic_and_dtype() -> None:
    c = np.linspace(-1, 1, 7, dtype=np.float32)
    p = henyey_greenstein(c, 0.0)
    assert p.dtype == np.float32
    np.testing.assert_allclose(p, 1 / (4 * math.pi), rtol=1e-6)
    with pytest.raises(FingerpsReconError, match="g"):
        henyey_greenstein(c, 1.0)


def test_phase_convention_switch_changes_the_single_scattering_term() -> None:
    n = Z
    light = _unit([1.0, 0.0, 1.0])  # 45 degrees: l.z = +0.707
    kw = {"rho": 0.0, "scale": 1.0}
    physical = hk_reflectance(n, light, Z, params=SkinParams(), **kw)
    paper = hk_reflectance(n, light, Z, params=SkinParams(phase=PhaseConvention.PAPER), **kw)
    c = float(light @ Z)
    assert physical > 0 and paper > 0
    # Everything but the phase function is the same, so the ratio is p(-c) / p(c).
    assert physical / paper == pytest.approx(
        henyey_greenstein(-c, 0.81) / henyey_greenstein(c, 0.81), rel=1e-12
    )
    assert paper / physical > 10  # forward vs backward scattering at g = 0.81, 45 degrees


def test_light_at_the_camera_is_back_scattering_in_the_physical_convention() -> None:
    params = SkinParams()
    value = hk_reflectance(Z, Z, Z, rho=0.0, scale=2.0, params=params)
    tau = params.optical_depth
    expected = 2.0 * henyey_greenstein(-1.0, 0.81) * 0.5 * (1 - math.exp(-2 * tau))
    assert value == pytest.approx(expected, rel=1e-12)


def test_full_expression_at_an_oblique_geometry() -> None:
    n = _unit([0.2, -0.3, 0.9])
    light = _unit([0.5, 0.4, 0.7])
    view = _unit([-0.1, 0.05, 1.0])
    params = SkinParams(d_mm=0.01)  # thin enough for the exponential to matter
    ci, cr, cphi = n @ light, n @ view, light @ view
    tau = params.optical_depth
    expected = (
        1.7
        * henyey_greenstein(-cphi, params.g)
        * ci
        / (ci + cr)
        * (1 - math.exp(-tau * (1 / ci + 1 / cr)))
        + 0.4 * ci
    )
    got = hk_reflectance(n, light, view, rho=0.4, scale=1.7, params=params)
    assert got == pytest.approx(expected, rel=1e-12)


def test_shadowed_and_hidden_points_are_zero_without_warnings() -> None:
    normals = _unit(
        [
            [1.0, 0.0, 0.0],  # c_i = 0 exactly (light along +y): grazing, and c_r = 0
            [-1.0, 0.0, 0.1],  # light towards +x: attached shadow, c_i < 0
            [0.0, 1.0, -0.1],  # light along z: c_i < 0 and c_r < 0
            [0.0, 1.0, 0.0],  # light along +y: c_i = 1 but c_r = 0, not seen by the camera
            [0.0, 0.0, 1.0],  # lit
        ]
    )
    lights = _unit([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], Z])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = hk_reflectance(normals, lights, Z, rho=0.5, scale=1.0)
    np.testing.assert_array_equal(out[:4], 0.0)
    assert out[4] > 0.5


def test_thick_layer_gives_the_lommel_seeliger_law() -> None:
    rng = np.random.default_rng(1)
    n = _unit(rng.normal(size=(500, 3)) * [1, 1, 0.3] + [0, 0, 1])
    light = _unit([0.3, -0.2, 1.0])
    thick = SkinParams(d_mm=50.0)
    ci, cr = n @ light, n[:, 2]
    lit = (ci > 0) & (cr > 0)
    c = -(light @ Z)
    lommel_seeliger = np.where(lit, 3.0 * henyey_greenstein(c, 0.81) * ci / (ci + cr), 0.0)
    got = hk_reflectance(n, light, Z, rho=0.0, scale=3.0, params=thick)
    np.testing.assert_allclose(got, lommel_seeliger, rtol=1e-12, atol=0)
    # With the paper's finger constants (tau_d ~ 4.1) it is already within 3e-4 of it.
    finger = hk_reflectance(n, light, Z, rho=0.0, scale=3.0, params=FINGER)
    np.testing.assert_allclose(finger, lommel_seeliger, rtol=3e-4, atol=0)
    assert np.any(finger != lommel_seeliger)


def test_thin_layer_limit_is_proportional_to_optical_depth() -> None:
    # tau -> 0: c_i/(c_i+c_r) (1 - exp(-tau (1/c_i + 1/c_r))) -> tau / c_r.
    n = _unit([0.1, 0.2, 1.0])
    light = _unit([-0.4, 0.1, 1.0])
    params = SkinParams(d_mm=1e-7)
    got = hk_reflectance(n, light, Z, rho=0.0, scale=1.0, params=params)
    expected = henyey_greenstein(-(light @ Z), params.g) * params.optical_depth / (n @ Z)
    assert got == pytest.approx(expected, rel=1e-6)


def test_zero_scale_is_lambertian() -> None:
    rng = np.random.default_rng(2)
    n = _unit(rng.normal(size=(300, 3)) + np.array([0, 0, 1.5]))
    light = _unit([0.6, 0.0, 0.8])
    rho = rng.uniform(0.2, 0.9, size=300)
    got = hk_reflectance(n, light, Z, rho=rho, scale=0.0)
    ci = n @ light
    expected = np.where((ci > 0) & (n[:, 2] > 0), rho * ci, 0.0)
    # c_i = n . l summed in another order here (BLAS) than in the model (einsum): each is
    # within 3 roundings of sum |n_k l_k| <= 1, however small c_i is (a relative tolerance
    # fails where it nearly cancels), and rho c_i adds one more: 8 u = 4 eps, absolute.
    np.testing.assert_allclose(got, expected, rtol=0, atol=4 * np.finfo(np.float64).eps)


def test_broadcasting_and_float32() -> None:
    h, w = 4, 5
    normals = np.zeros((h, w, 3), dtype=np.float32)
    normals[..., 2] = 1
    lights = _unit(np.array([[0, 0, 1], [0.5, 0, 1], [0, -0.5, 1]])).astype(np.float32)
    rho = np.full((h, w), 0.5, dtype=np.float32)
    out = hk_reflectance(
        normals, lights[:, None, None, :], np.array([0, 0, 1], np.float32), rho=rho, scale=1.0
    )
    assert out.shape == (3, h, w)
    assert out.dtype == np.float32
    ref = hk_reflectance(Z, lights.astype(np.float64), Z, rho=0.5, scale=1.0)
    np.testing.assert_allclose(out[:, 0, 0], ref, rtol=1e-6)
    assert np.all(out == out[:, :1, :1])
    with pytest.raises(FingerpsReconError, match="broadcast"):
        hk_reflectance(normals, lights, Z, rho=0.5, scale=1.0)


def test_skin_params_validation_and_constants() -> None:
    assert FINGER == SkinParams(0.12, 30.0, 4.5, 0.81, PhaseConvention.PHYSICAL)
    assert PLASTICINE.d_mm == 0.085 and PLASTICINE.sigma_s_per_mm == 50.0
    assert PLASTICINE.sigma_a_per_mm == 3.8 and PLASTICINE.g == 0.79
    assert FINGER.optical_depth == pytest.approx(0.12 * 34.5)
    assert SkinParams(phase="paper").phase is PhaseConvention.PAPER
    for bad in (
        {"d_mm": 0.0},
        {"sigma_s_per_mm": -1.0},
        {"sigma_a_per_mm": -0.1},
        {"g": 1.0},
        {"g": float("nan")},
        {"phase": "sideways"},
    ):
        with pytest.raises(FingerpsReconError):
            SkinParams(**bad)
