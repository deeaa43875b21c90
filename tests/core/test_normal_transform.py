"""Tests of fingerps_recon.photometric.normal_transform (paper Eq. 12)."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.normal_transform import enhance_ridges

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


def _reference(normals: np.ndarray, w: int, k: float, mask: np.ndarray | None) -> np.ndarray:
    """Eq. 12 written plainly in float64 over the whole image (the slow reference)."""
    src = np.array(normals, dtype=np.float64)
    if mask is not None:
        src[~mask] = 0
    src[~np.all(np.isfinite(src), axis=2)] = 0
    r = w // 2
    padded = np.pad(src, ((r, r), (r, r), (0, 0)))
    patch_sum = np.zeros_like(src)
    for dv in range(w):
        for du in range(w):
            patch_sum += padded[dv : dv + src.shape[0], du : du + src.shape[1]]

    def unit(v: np.ndarray) -> np.ndarray:
        norm = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)

    mean_dir = unit(patch_sum)
    mean_dir = np.where(np.any(mean_dir != 0, axis=2, keepdims=True), mean_dir, src)
    out = unit(src + k * (src - mean_dir))
    out[~np.any(src != 0, axis=2)] = 0
    return out


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize(("w", "k"), [(7, 2.5), (3, 1.0), (9, 0.0)])
@pytest.mark.parametrize("masked", [False, True])
def test_matches_the_plain_formula(dtype: type, w: int, k: float, masked: bool) -> None:
    rng = np.random.default_rng(1)
    n = _ridges() + 0.2 * rng.normal(size=(H, W, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[3, 4] = np.nan  # no normal
    n[7, 8] = 0.0  # no normal
    n[20, 30:40] = [0.0, 0.0, 0.0]
    mask = None
    if masked:
        v, u = np.mgrid[0:H, 0:W]
        mask = np.hypot(u - 40, v - 15) < 22  # touches the image's top and right edges
    n = n.astype(dtype)
    got = enhance_ridges(n, w=w, k=k, mask=mask)
    assert got.dtype == dtype
    expected = _reference(n, w, k, mask)
    np.testing.assert_allclose(got, expected, atol=2e-6 if dtype == np.float32 else 1e-12)


def test_empty_mask_gives_zeros() -> None:
    out = enhance_ridges(_ridges(), mask=np.zeros((H, W), dtype=bool))
    assert out.shape == (H, W, 3) and not out.any()
