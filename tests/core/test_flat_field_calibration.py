"""Tests of fingerps_calib.flat_field_calibration on synthetic smooth fields times texture."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import MIN_PORTION, Smoothing, flat_field_maps

H, W = 180, 240


def _near_light_field(u0: float, v0: float, height_px: float) -> np.ndarray:
    """Irradiance of a point light at height ``height_px`` above pixel (u0, v0) on a plane."""
    vv, uu = np.mgrid[0:H, 0:W]
    d2 = (uu - u0) ** 2 + (vv - v0) ** 2 + height_px**2
    return height_px / d2**1.5  # cos(incidence) / distance^2


def _texture(rng: np.random.Generator) -> np.ndarray:
    """Paper texture: 3 % rms, multiplicative, correlated over ~1 px."""
    t = ndimage.gaussian_filter(rng.normal(size=(H, W)), 1.0)
    return 1.0 + 0.03 * t / t.std()


def _white_target(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    fields = np.stack([
        _near_light_field(40.0, 30.0, 300.0),
        _near_light_field(200.0, 90.0, 400.0),
        _near_light_field(120.0, 250.0, 250.0),
    ])
    brightness = np.array([1.0, 0.7, 0.4])
    scaled = fields / fields.reshape(3, -1).max(axis=1)[:, None, None] * 200.0
    scaled *= brightness[:, None, None]
    images = scaled * _texture(rng) + 8.0 + rng.normal(0, 1.0, fields.shape)
    truth = fields / fields.reshape(3, -1).max(axis=1)[:, None, None]
    true_means = scaled.reshape(3, -1).mean(axis=1)
    return np.clip(np.round(images), 0, 255).astype(np.uint8), truth, true_means


@pytest.mark.parametrize(
    ("smoothing", "tolerance"), [(Smoothing.LOCAL_LINEAR, 0.01), (Smoothing.POLYNOMIAL, 0.01)]
)
def test_portions_follow_the_smooth_field_not_the_texture(smoothing, tolerance):
    rng = np.random.default_rng(0)
    images, truth, true_means = _white_target(rng)
    result = flat_field_maps(images, dark=np.full((H, W), 8.0), smoothing=smoothing)
    assert result.portions.dtype == np.float32 and result.portions.shape == (3, H, W)
    assert np.all(result.portions > 0) and np.all(result.portions <= 1)
    np.testing.assert_allclose(result.portions.reshape(3, -1).max(axis=1), 1.0)
    error = np.abs(result.portions / truth - 1.0)
    assert error.max() < 5 * tolerance, error.max()  # noisy dark corners included
    assert np.sqrt(np.mean(error**2)) < tolerance
    np.testing.assert_allclose(result.relative_intensities, true_means / true_means.max(),
                               rtol=0.01)
    assert result.relative_intensities[0] == 1.0


def test_local_linear_has_no_border_bias_on_a_linear_ramp():
    vv, uu = np.mgrid[0:H, 0:W]
    ramp = 50.0 + 0.5 * uu + 0.2 * vv
    result = flat_field_maps(ramp[None] / 255.0, smoothing_sigma_px=30.0)
    np.testing.assert_allclose(result.portions[0], ramp / ramp.max(), rtol=1e-5)


def test_dark_is_subtracted_per_led():
    rng = np.random.default_rng(1)
    images, truth, _ = _white_target(rng)
    dark = np.stack([np.full((H, W), 8.0)] * 3)
    with_dark = flat_field_maps(images, dark=dark)
    without = flat_field_maps(images)
    assert np.abs(with_dark.portions / truth - 1).max() < 0.03
    assert np.abs(without.portions / truth - 1).max() > 0.1  # the offset flattens the map


def test_inputs_not_modified():
    rng = np.random.default_rng(2)
    images, _, _ = _white_target(rng)
    before = images.copy()
    flat_field_maps(images)
    np.testing.assert_array_equal(images, before)


def test_saturated_led_is_named():
    rng = np.random.default_rng(3)
    images, _, _ = _white_target(rng)
    images[1, 20:60, 20:60] = 255
    with pytest.raises(FingerpsCalibError, match=r"LED 1:.*saturated.*exposure"):
        flat_field_maps(images)


def test_black_led_is_named():
    rng = np.random.default_rng(4)
    images, _, _ = _white_target(rng)
    images[2] = rng.integers(0, 3, (H, W))
    with pytest.raises(FingerpsCalibError, match=r"LED 2:.*nearly black"):
        flat_field_maps(images)


def test_float_images_use_full_scale_one():
    rng = np.random.default_rng(5)
    images, _, _ = _white_target(rng)
    result = flat_field_maps(images.astype(np.float32) / 255.0)
    assert result.portions.shape == (3, H, W)
    with pytest.raises(FingerpsCalibError, match=r"LED 0:.*saturated"):
        flat_field_maps(images.astype(np.float32))  # 0..255 floats: everything >= 1.0


def test_portions_are_clipped_above_zero():
    uu = np.mgrid[0:H, 0:W][1]
    ramp = np.maximum(uu - 60.0, 0.0)  # zero over the left quarter
    result = flat_field_maps(ramp[None] / 255.0, smoothing_sigma_px=5.0)
    assert result.portions.min() == pytest.approx(MIN_PORTION)


def test_bad_input_is_refused():
    with pytest.raises(FingerpsCalibError, match=r"\(K, H, W\)"):
        flat_field_maps(np.ones((H, W)))
    with pytest.raises(FingerpsCalibError, match=r"dark"):
        flat_field_maps(np.full((2, H, W), 0.5), dark=np.zeros((H + 1, W)))
    with pytest.raises(FingerpsCalibError, match=r"smoothing_sigma_px"):
        flat_field_maps(np.full((2, H, W), 0.5), smoothing_sigma_px=0.0)
    with pytest.raises(FingerpsCalibError, match=r"not positive"):
        flat_field_maps(np.full((1, H, W), 0.5), dark=np.full((H, W), 0.6),
                        min_signal_fraction=-1.0)
