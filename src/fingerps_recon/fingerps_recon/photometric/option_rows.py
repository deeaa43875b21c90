"""The parameter rows of `ReconstructionOptions` that recon_node and scan_node both declare.

One row each (``fingerps_ros.parameter_table``, no ROS), defaults from the options'
defaults, so that the two nodes describe, bound and check these parameters alike.
"""

from __future__ import annotations

from fingerps_recon.photometric.pipeline import ReconstructionOptions
from fingerps_ros.parameter_table import ParameterRow

_DEFAULTS = ReconstructionOptions()

HK_ITERATIONS = ParameterRow(
    "hk_iterations", _DEFAULTS.hk_iterations, "Levenberg-Marquardt iterations of the HK solver",
    min_value=1, max_value=100, integer=True)
MASK_THRESHOLD = ParameterRow(
    "mask_threshold", _DEFAULTS.mask_threshold,
    "Finger mask: fraction of the brightest level a pixel must exceed",
    min_value=0.01, max_value=0.9)
RIDGE_PATCH = ParameterRow(
    "w", _DEFAULTS.w, "Ridge enhancement patch size (odd), pixels", min_value=3, max_value=51,
    integer=True, check=lambda v: None if v % 2 == 1 else "must be odd")
RIDGE_GAIN = ParameterRow(
    "k", _DEFAULTS.k, "Ridge enhancement gain", min_value=0.0, max_value=20.0)
