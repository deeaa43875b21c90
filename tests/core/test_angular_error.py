"""Tests of fingerps_recon.photometric.angular_error."""

from __future__ import annotations

import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.angular_error import (
    AngularErrorSummary,
    angular_error_deg,
    summarize_angular_error,
)


def test_known_angles_tiny_and_opposite() -> None:
    z = [0.0, 0.0, 1.0]
    tiny = np.radians(1e-4)
    est = np.array(
        [z, [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.sin(tiny), 0, np.cos(tiny)], [0.0, 0.0, 2.0]]
    )
    err = angular_error_deg(est, np.array([z] * 5))
    np.testing.assert_allclose(err, [0.0, 90.0, 180.0, 1e-4, 0.0], rtol=1e-6, atol=1e-12)


def test_mask_and_missing_normals_give_nan() -> None:
    est = np.zeros((2, 2, 3))
    est[..., 2] = 1.0
    est[0, 1] = 0.0
    est[1, 1] = np.nan
    mask = np.array([[True, True], [False, True]])
    err = angular_error_deg(est, np.ones((2, 2, 3)), mask=mask)
    assert err[0, 0] == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))))
    assert np.all(np.isnan(err[[0, 1, 1], [1, 0, 1]]))


def test_summary() -> None:
    errors = np.append(np.arange(100, dtype=np.float64), [np.nan, 1000.0])
    mask = np.ones(102, dtype=bool)
    mask[-1] = False
    s = summarize_angular_error(errors, mask=mask)
    assert s == AngularErrorSummary(
        mean=49.5, median=49.5, p95=np.percentile(np.arange(100), 95), count=100
    )
    empty = summarize_angular_error(np.full(3, np.nan))
    assert empty.count == 0 and np.isnan(empty.mean)


def test_bad_shapes_raise() -> None:
    with pytest.raises(FingerpsReconError):
        angular_error_deg(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(FingerpsReconError):
        angular_error_deg(np.zeros((4, 3)), np.zeros((4, 3)), mask=np.ones(5, bool))
    with pytest.raises(FingerpsReconError):
        summarize_angular_error(np.zeros(4), mask=np.ones(3, bool))
