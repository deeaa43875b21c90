"""A quality verdict for one reconstruction: figures, thresholds, accept or reject and why.

The figures come from the burst and its reconstruction (:func:`quality_figures`); the
verdict compares them with thresholds (:func:`judge_quality`) and names every figure that
fails, with its value and limit, so an operator knows what to change (hold still, move the
finger into view, lower the exposure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.ridge_visibility import ridge_visibility


@dataclass(frozen=True)
class QualityThresholds:
    """Limits of an acceptable reconstruction (defaults: the simulated rig's margins).

    Attributes
    ----------
    min_coverage : float
        Reconstructed finger pixels / image pixels (the rig's fingertip fills ~0.5).
    max_saturated_fraction : float
        Finger pixels saturated in at least one LED's frame.
    max_dark_fraction : float
        Finger pixels in shadow in at least one LED's frame.
    min_ridge_visibility : float
        Ridge-band energy ratio of the normals (``ridge_visibility``; ~0.016 on the rig
        with the period estimated: a low bar, it catches maps without any ridges).
    max_motion_px : float
        Shift between the first LED's frame and its repeat, pixels (the rig's ridge period
        is 0.5 mm = 16.7 px; 2 px is about an eighth of it).
    max_residual : float
        Lambertian fit residual, rms / mean intensity.
    min_nfiq2 : float
        NFIQ 2 of the print (0-100, NIST's quality score); 0 = not judged. A print NFIQ 2
        cannot score fails a threshold above 0.
    """

    min_coverage: float = 0.1
    max_saturated_fraction: float = 0.02
    max_dark_fraction: float = 0.25
    min_ridge_visibility: float = 0.005
    max_motion_px: float = 2.0
    max_residual: float = 0.25
    min_nfiq2: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (math.isfinite(value) and value >= 0):
                raise FingerpsReconError(f"quality threshold {f.name} must be a number >= 0, "
                                         f"got {value}")


@dataclass(frozen=True)
class QualityFigures:
    """What :func:`judge_quality` looks at; NaN where a figure could not be measured."""

    coverage: float
    saturated_fraction: float
    dark_fraction: float
    ridge_visibility: float
    motion_px: float
    motion_correlation: float
    residual: float
    nfiq2: float = math.nan
    """NFIQ 2 of the print (``records.print_minutiae``), NaN before it is made or when NFIQ 2
    cannot score it."""


@dataclass(frozen=True)
class QualityVerdict:
    """Accept or reject, with one reason per failing figure."""

    accepted: bool
    reasons: tuple[str, ...]
    figures: QualityFigures


def quality_figures(
    images: np.ndarray,
    *,
    mask: np.ndarray,
    normals_ps: np.ndarray,
    full_scale: float,
    shadow_fraction: float = 0.02,
    saturation_fraction: float = 0.995,
    dark: np.ndarray | None = None,
    motion_px: float = math.nan,
    motion_correlation: float = math.nan,
    residual: float = math.nan,
    ridge_period_px: float | None = None,
) -> QualityFigures:
    """The figures of one reconstruction.

    Parameters
    ----------
    images : (K, H, W) uint8/uint16/float
        The burst's frames as captured (before dark subtraction). Not modified.
    mask : (H, W) bool
        The reconstructed finger pixels (``Reconstruction.mask``).
    normals_ps : (H, W, 3) float
        The normals (PS frame), for the ridge visibility.
    full_scale : float
        The sensor's largest value.
    shadow_fraction, saturation_fraction : float
        As ``ReconstructionOptions``: a pixel at or below ``shadow_fraction * full_scale``
        (after dark subtraction) is in shadow, at or above ``saturation_fraction *
        full_scale`` saturated.
    dark : (H, W), optional
        The burst's dark frame.
    motion_px, motion_correlation, residual : float
        Measured elsewhere (``burst_motion``, ``Reconstruction.residual``); NaN = not
        measured (not judged).
    ridge_period_px : float, optional
        Passed to ``ridge_visibility`` (None: estimated).
    """
    stack = np.asarray(images, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if stack.ndim != 3 or m.shape != stack.shape[1:]:
        raise FingerpsReconError(f"images {stack.shape} and mask {m.shape} do not fit")
    finger = int(m.sum())
    if finger == 0:
        return QualityFigures(0.0, math.nan, math.nan, math.nan, motion_px,
                              motion_correlation, residual)
    values = stack[:, m]
    saturated = np.any(values >= saturation_fraction * full_scale, axis=0)
    if dark is not None:
        values = values - np.asarray(dark, dtype=np.float32)[m]
    shadow = np.any(values <= shadow_fraction * full_scale, axis=0)
    try:
        visibility = ridge_visibility(normals_ps, mask=m, period_px=ridge_period_px)
    except FingerpsReconError:
        visibility = math.nan
    return QualityFigures(
        coverage=finger / m.size, saturated_fraction=float(saturated.mean()),
        dark_fraction=float(shadow.mean()), ridge_visibility=float(visibility),
        motion_px=float(motion_px), motion_correlation=float(motion_correlation),
        residual=float(residual))


def judge_quality(figures: QualityFigures, thresholds: QualityThresholds) -> QualityVerdict:
    """Accept when every measured figure is within its threshold; else name each failure.

    A NaN figure was not measured and is not judged, except the coverage and the ridge
    visibility, which every reconstruction has (NaN there means it could not be measured on
    this finger, a reason to reject).
    """
    f, t = figures, thresholds
    reasons = []
    if not f.coverage >= t.min_coverage:
        reasons.append(f"finger coverage {100 * f.coverage:.1f}% < {100 * t.min_coverage:.1f}%:"
                       " put the fingertip in the middle of the field")
    if f.saturated_fraction > t.max_saturated_fraction:
        reasons.append(f"saturated {100 * f.saturated_fraction:.1f}% of the finger > "
                       f"{100 * t.max_saturated_fraction:.1f}%: lower the exposure or LED level")
    if f.dark_fraction > t.max_dark_fraction:
        reasons.append(f"in shadow {100 * f.dark_fraction:.1f}% of the finger > "
                       f"{100 * t.max_dark_fraction:.1f}%: raise the exposure or centre the "
                       "finger")
    if not f.ridge_visibility >= t.min_ridge_visibility:
        reasons.append(f"ridge visibility {f.ridge_visibility:.3f} < "
                       f"{t.min_ridge_visibility:.3f}: the ridges are blurred (motion, focus)")
    if f.motion_px > t.max_motion_px:
        reasons.append(f"finger moved {f.motion_px:.2f} px during the burst > "
                       f"{t.max_motion_px:.2f} px: hold still")
    if f.residual > t.max_residual:
        reasons.append(f"fit residual {f.residual:.3f} > {t.max_residual:.3f}: the images do "
                       "not fit the calibrated lights (recalibrate, or ambient light)")
    if t.min_nfiq2 > 0 and not f.nfiq2 >= t.min_nfiq2:
        score = "NFIQ 2 could not score the print" if math.isnan(f.nfiq2) else \
            f"print quality NFIQ 2 {f.nfiq2:.0f} < {t.min_nfiq2:.0f}"
        reasons.append(f"{score}: {nfiq2_advice(f, t)}")
    return QualityVerdict(not reasons, tuple(reasons), figures)


#: A figure within this fraction of its limit counts as the likely cause of a poor print.
NEAR_LIMIT = 0.5


def nfiq2_advice(figures: QualityFigures, thresholds: QualityThresholds) -> str:
    """What the user should do about a poor print, as far as the other figures tell the
    causes apart: a finger small in view (move it closer), motion within the burst (hold
    still), ridges blurred though the finger held still (clean the lens)."""
    f, t = figures, thresholds
    advice = []
    if f.coverage < 2.0 * t.min_coverage:
        advice.append(f"move the finger closer (it covers {100 * f.coverage:.0f}% of the "
                      "image)")
    if f.motion_px > NEAR_LIMIT * t.max_motion_px:
        advice.append(f"hold still (it moved {f.motion_px:.1f} px)")
    elif f.ridge_visibility < 2.0 * t.min_ridge_visibility:
        advice.append(f"clean the lens (the ridges are faint, visibility "
                      f"{f.ridge_visibility:.3f}, though the finger held still)")
    if not advice:
        advice.append("clean the finger and the lens, hold still, and try again")
    return "; ".join(advice)
