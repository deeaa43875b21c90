"""Tests of fingerps_recon.photometric.ridge_visibility on synthetic ridge normal fields."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_recon.photometric.ridge_visibility import ridge_visibility

PERIOD = 12.0


def _field(size: int = 201, *, ridge_px: float = 0.4, noise: float = 0.0) -> tuple[
    np.ndarray, np.ndarray
]:
    """Normals (PS frame) of a dome with oblique sinusoidal ridges, and its disc mask."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    half = (size - 1) / 2
    x, y = (u - half) / (0.45 * size), -(v - half) / (0.45 * size)
    mask = x**2 + y**2 < 1
    z = np.sqrt(np.clip(1.2 - x**2 - y**2, 1e-6, None))
    ridges = ridge_px * np.sin(2 * np.pi * (u + 0.3 * v) / PERIOD)  # height, pixels
    gx = -x / z + np.gradient(ridges, axis=1)
    gy = -y / z + np.gradient(ridges, axis=0)
    n = np.stack([-gx, -gy, np.ones_like(x)], axis=-1)
    if noise:
        n += noise * np.random.default_rng(0).standard_normal(n.shape)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(mask[..., None], n, 0.0), mask


def _blur(normals: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    b = cv2.GaussianBlur(normals, (0, 0), sigma)
    b /= np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.where(mask[..., None], b, 0.0)


@pytest.mark.parametrize("period_px", [None, PERIOD])
def test_blurring_lowers_and_enhancing_raises_the_visibility(period_px: float | None) -> None:
    normals, mask = _field()
    score = ridge_visibility(normals, mask=mask, period_px=period_px)
    blurred = ridge_visibility(_blur(normals, mask, 2.0), mask=mask, period_px=period_px)
    enhanced = ridge_visibility(enhance_ridges(normals, w=7, k=2.5, mask=mask), mask=mask,
                                period_px=period_px)
    assert score > 0
    assert blurred < 0.5 * score
    assert enhanced > 2 * score
    # Monotone in the amount of blur (at a fixed band; an estimated period would follow
    # whatever peak is left once the ridges are blurred away).
    scores = [
        ridge_visibility(_blur(normals, mask, sigma), mask=mask, period_px=PERIOD)
        for sigma in (1.0, 2.0, 4.0)
    ]
    assert scores[0] > scores[1] > scores[2]


def test_noise_does_not_pass_for_ridges_and_enhancing_still_raises() -> None:
    normals, mask = _field(noise=0.03)
    clean, _ = _field()
    noisy = ridge_visibility(normals, mask=mask)
    assert noisy == pytest.approx(ridge_visibility(clean, mask=mask), rel=0.1)
    assert ridge_visibility(enhance_ridges(normals, mask=mask), mask=mask) > 2 * noisy


def test_estimated_period_matches_the_given_one() -> None:
    normals, mask = _field()
    # The same number whether the period is given or found from the spectrum.
    assert ridge_visibility(normals, mask=mask) == pytest.approx(
        ridge_visibility(normals, mask=mask, period_px=PERIOD), rel=0.05
    )


def test_no_ridges_scores_near_zero_and_more_ridge_scores_more() -> None:
    flat, mask = _field(ridge_px=0.0)
    weak, _ = _field(ridge_px=0.2)
    strong, _ = _field(ridge_px=0.4)
    zero = ridge_visibility(flat, mask=mask, period_px=PERIOD)
    assert zero < 1e-3 * ridge_visibility(strong, mask=mask, period_px=PERIOD)
    assert ridge_visibility(weak, mask=mask) < ridge_visibility(strong, mask=mask)


def test_outside_the_mask_does_not_count_and_inputs_are_unchanged() -> None:
    normals, mask = _field()
    copy = normals.copy()
    score = ridge_visibility(normals, mask=mask, period_px=PERIOD)
    garbage = normals.copy()
    garbage[~mask] = np.random.default_rng(1).standard_normal((np.count_nonzero(~mask), 3))
    assert ridge_visibility(garbage, mask=mask, period_px=PERIOD) == pytest.approx(score)
    np.testing.assert_array_equal(normals, copy)


@pytest.mark.parametrize(
    ("normals", "mask", "period", "message"),
    [
        (np.zeros((10, 10)), np.ones((10, 10), bool), None, "normals"),
        (np.zeros((10, 10, 3)), np.ones((10, 9), bool), None, "mask"),
        (np.zeros((10, 10, 3)), np.ones((10, 10), np.uint8), None, "mask"),
        (np.dstack([np.zeros((40, 40, 2)), np.ones((40, 40))]), np.ones((40, 40), bool), 1.0,
         "period_px"),
        (np.dstack([np.zeros((20, 20, 2)), np.ones((20, 20))]), np.ones((20, 20), bool), 12.0,
         "fewer than"),
    ],
)
def test_bad_inputs_raise(normals: np.ndarray, mask: np.ndarray, period: float | None,
                          message: str) -> None:
    with pytest.raises(FingerpsReconError, match=message):
        ridge_visibility(normals, mask=mask, period_px=period)
