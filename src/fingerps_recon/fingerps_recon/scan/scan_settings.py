"""What one Scan goal runs with: the scan node's parameters and a goal's own values.

`SCAN_PARAMETERS` is the scan node's parameter table (`fingerps_ros.parameter_table`: name,
default, description, range, check), plain data the node declares; `GOAL_PARAMETERS` are
the ones a goal may override (``Scan.Goal.overrides``): reconstruction and judgement.
`goal_settings` turns the values in force for a goal into `ScanSettings`, or says
everything that is impossible about it.

No ROS here.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from fingerps_recon.errors import ImpossibleGoalError
from fingerps_recon.photometric import option_rows as rows
from fingerps_recon.photometric.full_scale import MONO16_FULL_SCALE
from fingerps_recon.photometric.pipeline import Model, Projection, ReconstructionOptions
from fingerps_recon.scan.quality import QualityThresholds
from fingerps_ros.parameter_table import ParameterRow

MAX_BURSTS = 20

GOAL_PARAMETERS = (
    "model", "hk_iterations", "projection", "mask_threshold", "enhance", "w", "k",
    "working_distance", "presence_threshold", "presence_min_coverage", "max_motion_px",
    "max_retakes", "min_coverage", "max_saturated_fraction", "max_dark_fraction",
    "min_ridge_visibility", "max_residual", "min_nfiq2")
"""Parameters a goal may override (``Scan.Goal.overrides``)."""


_T = QualityThresholds()
SCAN_PARAMETERS: tuple[ParameterRow, ...] = (
    replace(rows.MODEL, description=rows.MODEL.description + "; a goal's model field "
            "overrides it"),
    rows.PROJECTION, rows.HK_ITERATIONS, rows.MASK_THRESHOLD, rows.ENHANCE, rows.RIDGE_PATCH,
    rows.RIDGE_GAIN, rows.WORKING_DISTANCE,
    MONO16_FULL_SCALE,
    ParameterRow("timeout", 30.0, "Seconds a goal may take when it gives timeout 0",
                 0.1, 3600.0),
    ParameterRow("capture_timeout", 10.0,
                 "Seconds to wait for the driver's capture_burst answer", 0.1, 120.0),
    ParameterRow("presence_threshold", 0.05,
                 "Finger presence: lit minus dark must exceed this fraction of full scale",
                 0.001, 0.9),
    ParameterRow("presence_min_coverage", 0.1,
                 "Finger presence: the bright region must cover this fraction of the image",
                 0.0, 1.0),
    ParameterRow("presence_period", 0.2,
                 "Seconds between presence checks while waiting for a finger", 0.0, 10.0),
    ParameterRow("max_motion_px", 2.0,
                 "A burst whose finger moved more than this (first LED vs its repeat, "
                 "pixels) is retaken; ~1/8 of the rig's ridge period (0.5 mm = 16.7 px)",
                 0.0, 100.0),
    ParameterRow("max_retakes", 5, "Bursts retaken for motion before the goal is aborted",
                 0, 100, integer=True),
    ParameterRow("min_coverage", _T.min_coverage,
                 "Verdict: reconstructed finger pixels / image pixels at least", 0.0, 1.0),
    ParameterRow("max_saturated_fraction", _T.max_saturated_fraction,
                 "Verdict: finger pixels saturated in some frame at most", 0.0, 1.0),
    ParameterRow("max_dark_fraction", _T.max_dark_fraction,
                 "Verdict: finger pixels in shadow in some frame at most", 0.0, 1.0),
    ParameterRow("min_ridge_visibility", _T.min_ridge_visibility,
                 "Verdict: ridge-band energy ratio of the normals at least", 0.0, 100.0),
    ParameterRow("max_residual", _T.max_residual,
                 "Verdict: Lambertian fit residual (rms / mean intensity) at most", 0.0, 10.0),
    ParameterRow("min_nfiq2", _T.min_nfiq2,
                 "Verdict: NFIQ 2 of the print (NIST's 0-100 quality score) at least; 0 = not "
                 "judged. The reason tells the user what to do (move closer, hold still, "
                 "clean the lens) where the other figures tell it", 0.0, 100.0),
    ParameterRow("recorder", "recorder",
                 "The recorder node (relative to the namespace) whose bag the result names; "
                 "empty = none", read_only=True),
)
"""The scan node's parameters, in the order it declares them."""


@dataclass(frozen=True)
class ScanSettings:
    """Everything one goal runs with (the node's parameters with the goal's overrides)."""

    bursts: int
    timeout_s: float
    options: ReconstructionOptions
    thresholds: QualityThresholds
    presence_threshold: float
    presence_min_coverage: float
    max_retakes: int
    presence_period_s: float = 0.2
    records: bool = False
    """Make the print's WSQ, ISO/IEC 19794-2 and ANSI/NIST-ITL records (``Scan.Goal.records``)."""


def goal_settings(*, bursts: int, model: str, timeout_s: float, values: Mapping[str, Any],
                  problems: Iterable[str] = (), default_timeout_s: float,
                  presence_period_s: float, records: bool = False) -> ScanSettings:
    """The settings of a goal.

    Parameters
    ----------
    bursts, model, timeout_s, records
        The goal's fields (``model`` empty and ``timeout_s`` 0: the parameters').
    values : Mapping[str, Any]
        Every `GOAL_PARAMETERS` value in force for the goal (overrides applied).
    problems : Iterable[str]
        What is wrong with the goal's overrides, reported after the fields' problems.
    default_timeout_s, presence_period_s
        The node's ``timeout`` and ``presence_period``.

    Raises
    ------
    ImpossibleGoalError
        Naming every problem, ``; ``-separated.
    FingerpsReconError
        A threshold the quality module refuses.
    """
    found = []
    if bursts < 1 or bursts > MAX_BURSTS:
        found.append(f"bursts {bursts}: must be 1..{MAX_BURSTS}")
    models = [m.value for m in Model]
    if model and model not in models:
        found.append(f"unknown model {model!r}: use {' or '.join(models)}")
    if not math.isfinite(timeout_s) or timeout_s < 0:
        found.append(f"timeout {timeout_s}: must be > 0 seconds (0 = the node's "
                     "timeout parameter)")
    found.extend(problems)
    values = dict(values)
    if model in models:
        values["model"] = model
    if found:
        raise ImpossibleGoalError("; ".join(found))
    options = ReconstructionOptions(
        model=Model(values["model"]), hk_iterations=int(values["hk_iterations"]),
        projection=Projection(values["projection"]),
        mask_threshold=float(values["mask_threshold"]), enhance=bool(values["enhance"]),
        w=int(values["w"]), k=float(values["k"]),
        working_distance_m=float(values["working_distance"]))
    thresholds = QualityThresholds(
        min_coverage=float(values["min_coverage"]),
        max_saturated_fraction=float(values["max_saturated_fraction"]),
        max_dark_fraction=float(values["max_dark_fraction"]),
        min_ridge_visibility=float(values["min_ridge_visibility"]),
        max_motion_px=float(values["max_motion_px"]),
        max_residual=float(values["max_residual"]), min_nfiq2=float(values["min_nfiq2"]))
    return ScanSettings(
        bursts=int(bursts), timeout_s=timeout_s or default_timeout_s, options=options,
        thresholds=thresholds, presence_threshold=float(values["presence_threshold"]),
        presence_min_coverage=float(values["presence_min_coverage"]),
        max_retakes=int(values["max_retakes"]), presence_period_s=presence_period_s,
        records=bool(records))
