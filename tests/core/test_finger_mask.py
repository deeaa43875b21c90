"""The finger mask (photometric.finger_mask): the largest bright region of a burst."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.finger_mask import finger_mask


def _burst(dtype: type) -> np.ndarray:
    """Seven 8-bit-valued images: a bright disc (the finger), a small speck, dim noise."""
    rng = np.random.default_rng(7)
    v, u = np.mgrid[0:60, 0:80]
    disc = (v - 25) ** 2 + (u - 35) ** 2 < 12**2
    images = rng.integers(0, 12, (7, 60, 80)).astype(np.float64)
    images[:, disc] += rng.integers(120, 200, (7, int(disc.sum())))
    images[:, 5:7, 70:72] = 250  # a speck: removed by the opening
    return images.astype(dtype), disc


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_the_disc_is_found_the_same_in_every_dtype(dtype: type) -> None:
    # uint8 bursts take the histogram's percentile, the others numpy's: the same level.
    images, disc = _burst(dtype)
    mask = finger_mask(images)
    assert mask.dtype == bool and mask.shape == disc.shape
    np.testing.assert_array_equal(mask, finger_mask(images.astype(np.float64)))
    assert (mask & disc).sum() > 0.97 * disc.sum() and not (mask & ~disc).any()


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_saturated_values_count_as_dark(dtype: type) -> None:
    # A saturated region larger than the finger is the largest bright region unless its
    # values are left out as saturated; the input is not modified.
    images, disc = _burst(dtype)
    images[:, 45:60, :] = 255
    before = images.copy()
    assert not finger_mask(images)[disc].all()
    mask = finger_mask(images, saturation_level=254.5)
    np.testing.assert_array_equal(images, before)
    assert (mask & disc).sum() > 0.97 * disc.sum() and not mask[45:, :].any()


def test_bad_arguments_raise() -> None:
    with pytest.raises(FingerpsReconError, match="K, H, W"):
        finger_mask(np.ones((5, 5)))
    with pytest.raises(FingerpsReconError, match="threshold"):
        finger_mask(np.ones((3, 5, 5)), threshold=1.5)
