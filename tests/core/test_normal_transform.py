"""Tests of fingerps_recon.normal_transform (paper Eq. 12)."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.angular_error import angular_error_deg
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.normal_transform import enhance_ridges

H, W = 40, 60


def _ridges(amplitude: float = 0.15, period: float = 8.0) -> np.ndarray:
    """Normals of the ridged surface h = a sin(2 pi u / period) (PS frame)."""
    u = np.arange(W, dtype=np.float64)
    slope = amplitude * 2 * np.pi / period * np.cos(2 * np.pi * u / period)
    n = np.zeros((H, W, 3))
    n[..., 0] = -slope
    n[..., 2] = 1.0
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _tilt_deg(n: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(n[..., :2], axis=-1), n[..., 2]))


def test_zero_gain_is_identity() -> None:
    rng = np.random.default_rng(0)
    n = rng.normal(size=(H, W, 3)) + np.array([0, 0, 2])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    out = enhance_ridges(n, k=0.0)
    assert out.dtype == np.float64
    np.testing.assert_allclose(out, n, atol=1e-12)


def test_flat_region_is_unchanged_up_to_the_border() -> None:
    n = np.zeros((H, W, 3), dtype=np.float32)
    n[...] = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    out = enhance_ridges(n, w=7, k=2.5)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, n, atol=1e-6)


def test_ridge_contrast_increases_and_input_untouched() -> None:
    n = _ridges()
    before = n.copy()
    out = enhance_ridges(n, w=7, k=2.5)
    np.testing.assert_array_equal(n, before)
    assert out is not n
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, rtol=1e-12)
    inner = (slice(5, -5), slice(5, -5))
    # Angle between neighbouring normals grows, and so does the tilt amplitude.
    step_in = angular_error_deg(n[:, 1:], n[:, :-1])[inner].mean()
    step_out = angular_error_deg(out[:, 1:], out[:, :-1])[inner].mean()
    assert step_out > 2.0 * step_in
    assert _tilt_deg(out)[inner].max() > 2.0 * _tilt_deg(n)[inner].max()
    # The enhancement keeps the ridges where they are: the x slope keeps its sign.
    assert np.all(np.sign(out[inner][..., 0]) == np.sign(n[inner][..., 0]))
    # Larger gain, more contrast.
    stronger = enhance_ridges(n, w=7, k=5.0)
    assert _tilt_deg(stronger)[inner].max() > _tilt_deg(out)[inner].max()


def test_mask_excludes_outside_neighbours_and_zeroes_outside() -> None:
    n = _ridges()
    mask = np.zeros((H, W), dtype=bool)
    mask[10:30, 15:45] = True
    wild = n.copy()
    wild[~mask] = [1.0, 0.0, 0.0]  # outside normals must not influence the inside
    cleared = np.where(mask[..., None], n, 0.0)
    a = enhance_ridges(wild, mask=mask)
    b = enhance_ridges(cleared)
    np.testing.assert_allclose(a, b, atol=1e-12)
    assert np.all(a[~mask] == 0)
    assert np.all(np.abs(np.linalg.norm(a[mask], axis=-1) - 1) < 1e-12)


def test_isolated_normal_is_kept() -> None:
    n = np.zeros((H, W, 3))
    n[5, 5] = [0.0, 0.6, 0.8]
    out = enhance_ridges(n)
    np.testing.assert_allclose(out[5, 5], [0.0, 0.6, 0.8], atol=1e-12)
    assert np.count_nonzero(np.any(out != 0, axis=-1)) == 1


@pytest.mark.parametrize(
    "kwargs", [{"w": 6}, {"w": 1}, {"w": 7.0}, {"w": True}, {"k": -1.0}, {"k": float("nan")}]
)
def test_bad_options_raise(kwargs: dict) -> None:
    with pytest.raises(FingerpsReconError):
        enhance_ridges(_ridges(), **kwargs)


def test_bad_shapes_raise() -> None:
    with pytest.raises(FingerpsReconError, match="normals"):
        enhance_ridges(np.zeros((H, W)))
    with pytest.raises(FingerpsReconError, match="mask"):
        enhance_ridges(_ridges(), mask=np.ones((H, W + 1), dtype=bool))
