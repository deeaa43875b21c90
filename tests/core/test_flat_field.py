"""Tests of fingerps_recon.photometric.flat_field (paper Eq. 11)."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.flat_field import apply_flat_field

K, H, W = 3, 12, 16


def _portions() -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    fields = np.stack(
        [
            1.0 / (1.0 + ((u - cu) ** 2 + (v - cv) ** 2) / 100.0)
            for cu, cv in [(0, 0), (8, 6), (15, 11)]
        ]
    )
    return fields / fields.max(axis=(1, 2), keepdims=True)


def test_uniform_scene_becomes_uniform() -> None:
    portions = _portions()
    albedo = np.random.default_rng(0).uniform(0.2, 0.8, size=(H, W))
    strengths = np.array([100.0, 50.0, 80.0])[:, None, None]
    images = strengths * portions * albedo
    corrected = apply_flat_field(images, portions)
    assert corrected.dtype == np.float64
    np.testing.assert_allclose(corrected, strengths * albedo, rtol=1e-12)


def test_small_portions_are_clipped() -> None:
    portions = np.full((K, H, W), 0.5)
    portions[0, 0, 0] = 0.0
    portions[1, 0, 0] = 0.001
    images = np.ones((K, H, W), dtype=np.float32)
    corrected = apply_flat_field(images, portions, min_portion=0.05)
    assert corrected.dtype == np.float32
    assert corrected[0, 0, 0] == pytest.approx(20.0)
    assert corrected[1, 0, 0] == pytest.approx(20.0)
    assert corrected[2, 0, 0] == pytest.approx(2.0)
    assert np.all(np.isfinite(apply_flat_field(images, portions)))


def test_integer_images_give_float32_and_inputs_untouched() -> None:
    portions = _portions()
    images = np.full((K, H, W), 200, dtype=np.uint8)
    before_i, before_p = images.copy(), portions.copy()
    corrected = apply_flat_field(images, portions)
    assert corrected.dtype == np.float32
    np.testing.assert_allclose(corrected, 200 / np.maximum(portions, 0.02), rtol=1e-6)
    np.testing.assert_array_equal(images, before_i)
    np.testing.assert_array_equal(portions, before_p)


def test_shape_mismatch_names_both_shapes() -> None:
    with pytest.raises(FingerpsReconError, match=r"\(3, 12, 16\).*\(3, 12, 15\)"):
        apply_flat_field(np.ones((K, H, W)), np.ones((K, H, W - 1)))


@pytest.mark.parametrize(
    ("images", "portions", "kwargs"),
    [
        (np.ones((H, W)), np.ones((H, W)), {}),
        (np.ones((K, H, W)), np.full((K, H, W), np.nan), {}),
        (np.ones((K, H, W)), np.ones((K, H, W)), {"min_portion": 0.0}),
        (np.ones((K, H, W)), np.ones((K, H, W)), {"min_portion": 1.5}),
    ],
)
def test_bad_inputs_raise(images: np.ndarray, portions: np.ndarray, kwargs: dict) -> None:
    with pytest.raises(FingerpsReconError):
        apply_flat_field(images, portions, **kwargs)
