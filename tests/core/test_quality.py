"""quality: figures from a burst and its reconstruction; the verdict names each failure."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.pipeline import reconstruct
from fingerps_recon.scan.quality import (
    QualityFigures,
    QualityThresholds,
    judge_quality,
    quality_figures,
)

GOOD = QualityFigures(coverage=0.5, saturated_fraction=0.0, dark_fraction=0.05,
                      ridge_visibility=0.02, motion_px=0.1, motion_correlation=0.9,
                      residual=0.08)


def test_good_figures_are_accepted_without_reasons() -> None:
    verdict = judge_quality(GOOD, QualityThresholds())
    assert verdict.accepted and verdict.reasons == ()


@pytest.mark.parametrize(("change", "words"), [
    ({"coverage": 0.01}, "finger coverage 1.0%"),
    ({"saturated_fraction": 0.1}, "saturated 10.0%"),
    ({"dark_fraction": 0.5}, "in shadow 50.0%"),
    ({"ridge_visibility": math.nan}, "ridge visibility nan"),
    ({"motion_px": 3.0}, "moved 3.00 px"),
    ({"residual": 0.5}, "fit residual 0.500"),
])
def test_each_failing_figure_is_named(change: dict, words: str) -> None:
    figures = QualityFigures(**{**vars(GOOD), **change})
    verdict = judge_quality(figures, QualityThresholds())
    assert not verdict.accepted and len(verdict.reasons) == 1
    assert words in verdict.reasons[0]


def test_unmeasured_motion_and_residual_are_not_judged() -> None:
    figures = QualityFigures(**{**vars(GOOD), "motion_px": math.nan, "residual": math.nan})
    assert judge_quality(figures, QualityThresholds()).accepted


def test_nfiq2_is_judged_only_with_a_threshold() -> None:
    poor = QualityFigures(**{**vars(GOOD), "nfiq2": 12.0})
    assert judge_quality(poor, QualityThresholds()).accepted  # min_nfiq2 0: not judged
    assert judge_quality(poor, QualityThresholds(min_nfiq2=12.0)).accepted
    verdict = judge_quality(poor, QualityThresholds(min_nfiq2=40.0))
    assert not verdict.accepted and verdict.reasons[0].startswith("print quality NFIQ 2 12 < 40")
    unscored = QualityFigures(**{**vars(GOOD), "nfiq2": math.nan})
    assert "NFIQ 2 could not score the print" in judge_quality(
        unscored, QualityThresholds(min_nfiq2=40.0)).reasons[0]


@pytest.mark.parametrize(("change", "advice", "not_advice"), [
    ({"coverage": 0.15}, "move the finger closer", "hold still"),
    ({"motion_px": 1.5}, "hold still", "clean the lens"),
    ({"ridge_visibility": 0.006}, "clean the lens", "hold still"),
    ({}, "clean the finger and the lens", "move the finger closer"),
])
def test_a_poor_print_s_reason_says_what_to_do(change: dict, advice: str,
                                              not_advice: str) -> None:
    # Each of these figures passes its own threshold: only NFIQ 2 fails, and the others tell
    # the user which way to go.
    figures = QualityFigures(**{**vars(GOOD), "nfiq2": 20.0, **change})
    verdict = judge_quality(figures, QualityThresholds(min_nfiq2=40.0))
    assert len(verdict.reasons) == 1
    assert advice in verdict.reasons[0] and not_advice not in verdict.reasons[0]


def test_negative_thresholds_are_refused() -> None:
    with pytest.raises(FingerpsReconError, match="max_motion_px"):
        QualityThresholds(max_motion_px=-1.0)


def test_figures_of_a_simulated_reconstruction() -> None:
    rig = SimulatedRig(RigConfig())
    rng = np.random.default_rng(0)
    images = rig.render_burst(Scene.FINGER, rng=rng)
    dark = rig.render(Scene.FINGER, [], rng=rng)
    rec = reconstruct(images, lights_ps=rig.light_directions_ps(),
                      camera_matrix=rig.camera_matrix, full_scale=255, dark=dark)
    assert rec.residual is not None and 0.0 < rec.residual < 0.25
    figures = quality_figures(images, mask=rec.mask, normals_ps=rec.normals_ps,
                              full_scale=255, dark=dark, residual=rec.residual, motion_px=0.0)
    assert 0.4 < figures.coverage < 0.7
    assert figures.saturated_fraction < 0.01 and figures.dark_fraction < 0.25
    assert figures.ridge_visibility > QualityThresholds().min_ridge_visibility
    assert judge_quality(figures, QualityThresholds()).accepted
    # an over-exposed burst: most of the finger saturates
    bright = np.clip(images.astype(np.int32) * 4, 0, 255).astype(np.uint8)
    saturated = quality_figures(bright, mask=rec.mask, normals_ps=rec.normals_ps,
                                full_scale=255, dark=dark)
    verdict = judge_quality(saturated, QualityThresholds())
    assert not verdict.accepted and "saturated" in verdict.reasons[0]
