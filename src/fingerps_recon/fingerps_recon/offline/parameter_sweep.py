"""A sweep of reconstruction settings over bursts, without ROS: the core of ``offline_tune``.

A `BurstInput` holds everything `pipeline.reconstruct` needs for one burst (from a bag or a
DiLiGenT-layout folder) and, where known, the ground-truth normals. A `Setting` is one
(model, w, k): the model decides the normals (one solve per burst and model), w and k only
the ridge enhancement (paper Eq. 12) applied to those normals, so `sweep_burst` solves once
per model and enhances once per (w, k). `score` gives the figures of one setting:
ridge visibility of the enhanced and of the plain normals, and the angular error of the
plain normals against the ground truth.

No rclpy, no file I/O.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.angular_error import angular_error_deg, summarize_angular_error
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_recon.photometric.pipeline import (
    Model,
    Reconstruction,
    ReconstructionOptions,
    reconstruct,
)
from fingerps_recon.photometric.ridge_visibility import ridge_visibility


@dataclass(frozen=True)
class BurstInput:
    """One burst and its calibration, as arrays (see `pipeline.reconstruct`).

    ``normal_gt`` : (H, W, 3) float, PS frame, or None. ``name`` labels the outputs.
    """

    name: str
    images: np.ndarray
    lights_ps: np.ndarray
    camera_matrix: np.ndarray
    full_scale: float
    intensities: np.ndarray | None = None
    portions: np.ndarray | None = None
    dark: np.ndarray | None = None
    mask: np.ndarray | None = None
    led_positions_optical: np.ndarray | None = None
    normal_gt: np.ndarray | None = None
    ridge_period_px: float | None = None
    """Ridge period for `ridge_visibility`, the same for every setting; None: estimated
    from each map (a period estimate may find the finger's shape instead of its ridges on
    small images; give it then)."""
    base_options: ReconstructionOptions = field(default_factory=ReconstructionOptions)


@dataclass(frozen=True)
class Setting:
    """One point of the sweep."""

    model: Model
    w: int
    k: float

    @property
    def label(self) -> str:
        """E.g. ``lambert_w7_k2.5``: a file name and a column heading."""
        return f"{self.model.value}_w{self.w}_k{self.k:g}"


@dataclass(frozen=True)
class SettingScore:
    """Figures of one setting on one burst (NaN where not defined)."""

    ridge_visibility: float
    """Of the enhanced normals."""
    ridge_visibility_plain: float
    """Of the normals before enhancement (the model's alone)."""
    error_mean_deg: float
    error_median_deg: float
    valid_pixels: int


def settings_grid(models: Iterable[Model], ws: Iterable[int],
                  ks: Iterable[float]) -> list[Setting]:
    """Every combination, models outermost.

    Raises
    ------
    FingerpsReconError
        An even or too small w, a negative k, or an empty list.
    """
    models, ws, ks = list(models), list(ws), list(ks)
    if not models or not ws or not ks:
        raise FingerpsReconError("each of --model, --w and --k needs at least one value")
    bad_w = [w for w in ws if w < 3 or w % 2 == 0]
    if bad_w:
        raise FingerpsReconError(f"w must be odd and at least 3, got {bad_w}")
    if any(k < 0 for k in ks):
        raise FingerpsReconError(f"k must not be negative, got {ks}")
    return [Setting(m, int(w), float(k)) for m, w, k in itertools.product(models, ws, ks)]


def solve(burst: BurstInput, model: Model) -> Reconstruction:
    """The burst's reconstruction under ``model`` (no enhancement)."""
    options = ReconstructionOptions(**{**burst.base_options.__dict__, "model": model,
                                       "enhance": False})
    return reconstruct(
        burst.images, lights_ps=burst.lights_ps, camera_matrix=burst.camera_matrix,
        full_scale=burst.full_scale, intensities=burst.intensities, portions=burst.portions,
        dark=burst.dark, mask=burst.mask, led_positions_optical=burst.led_positions_optical,
        options=options)


def _visibility(normals: np.ndarray, mask: np.ndarray, period_px: float | None) -> float:
    try:
        return float(ridge_visibility(normals, mask=mask, period_px=period_px))
    except FingerpsReconError:
        return math.nan  # too few pixels, no period found


def score(normals: np.ndarray, enhanced: np.ndarray, mask: np.ndarray,
          normal_gt: np.ndarray | None, *, period_px: float | None = None) -> SettingScore:
    """Figures of one setting.

    Parameters
    ----------
    normals, enhanced : (H, W, 3) float32
        Plain and enhanced normals, PS frame.
    mask : (H, W) bool
    normal_gt : (H, W, 3) float or None
        Ground truth (PS frame); the error is of the plain normals, over the mask and the
        truth's non-zero pixels.
    period_px : float, optional
        Ridge period for `ridge_visibility` (NaN when it cannot be measured).
    """
    mean = median = math.nan
    if normal_gt is not None:
        region = mask & (np.linalg.norm(normal_gt, axis=2) > 0)
        stats = summarize_angular_error(angular_error_deg(normals, normal_gt, mask=region))
        mean, median = stats.mean, stats.median
    return SettingScore(
        ridge_visibility=_visibility(enhanced, mask, period_px),
        ridge_visibility_plain=_visibility(normals, mask, period_px),
        error_mean_deg=mean, error_median_deg=median, valid_pixels=int(mask.sum()))


@dataclass(frozen=True)
class SweptSetting:
    """A setting's enhanced normals and figures on one burst."""

    setting: Setting
    enhanced_ps: np.ndarray
    score: SettingScore
    time_ms: float


def sweep_burst(burst: BurstInput, model: Model,
                settings: Sequence[Setting]) -> tuple[Reconstruction, list[SweptSetting]]:
    """Solve once under ``model``, then enhance and score every setting of that model."""
    t0 = time.perf_counter()
    rec = solve(burst, model)
    solve_ms = (time.perf_counter() - t0) * 1e3
    swept = []
    for setting in settings:
        if setting.model is not model:
            continue
        t1 = time.perf_counter()
        enhanced = np.where(rec.mask[..., None],
                            enhance_ridges(rec.normals_ps, w=setting.w, k=setting.k,
                                           mask=rec.mask), 0.0).astype(np.float32)
        figures = score(rec.normals_ps, enhanced, rec.mask, burst.normal_gt,
                        period_px=burst.ridge_period_px)
        swept.append(SweptSetting(setting, enhanced, figures,
                                  solve_ms + (time.perf_counter() - t1) * 1e3))
    return rec, swept

