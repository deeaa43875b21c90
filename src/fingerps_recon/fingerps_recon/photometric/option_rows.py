"""The parameter rows of `ReconstructionOptions` that recon_node and scan_node both declare.

One row each (``fingerps_ros.parameter_table``, no ROS), its default read from
:data:`NODE_OPTIONS`, so that the two nodes start from, describe, bound and check these
parameters alike and every default is written once, in the options' dataclass.
"""

from __future__ import annotations

from dataclasses import replace

from fingerps_recon.photometric.pipeline import Model, Projection, ReconstructionOptions
from fingerps_ros.parameter_table import ParameterRow, one_of

NODE_OPTIONS = replace(ReconstructionOptions(), model=Model.HK, enhance=True)
"""The options recon_node and scan_node start with: the library's defaults
(`ReconstructionOptions`), but the paper's skin model and the ridge-enhanced normal map."""

MODEL = ParameterRow(
    "model", NODE_OPTIONS.model.value,
    "Reflectance model of the normals: hk (the paper's simplified Hanrahan-Krueger skin model, "
    "initialised from lambert; the most accurate normals) or lambert (Lambertian photometric "
    "stereo, faster)", check=one_of(*(m.value for m in Model)))
PROJECTION = ParameterRow(
    "projection", NODE_OPTIONS.projection.value,
    "Camera model of the views, the integration and the points: perspective (from the "
    "burst's camera_info) or orthographic", check=one_of(*(p.value for p in Projection)))
HK_ITERATIONS = ParameterRow(
    "hk_iterations", NODE_OPTIONS.hk_iterations,
    "Levenberg-Marquardt iterations of the HK solver", min_value=1, max_value=100,
    integer=True)
MASK_THRESHOLD = ParameterRow(
    "mask_threshold", NODE_OPTIONS.mask_threshold,
    "Finger mask: fraction of the brightest level a pixel must exceed",
    min_value=0.01, max_value=0.9)
ENHANCE = ParameterRow(
    "enhance", NODE_OPTIONS.enhance,
    "Publish the normal map after ridge enhancement (paper Eq. 12); the normals always "
    "carry the unenhanced normals")
RIDGE_PATCH = ParameterRow(
    "w", NODE_OPTIONS.w, "Ridge enhancement patch size (odd), pixels", min_value=3,
    max_value=51, integer=True, check=lambda v: None if v % 2 == 1 else "must be odd")
RIDGE_GAIN = ParameterRow(
    "k", NODE_OPTIONS.k, "Ridge enhancement gain", min_value=0.0, max_value=20.0)
WORKING_DISTANCE = ParameterRow(
    "working_distance", NODE_OPTIONS.working_distance_m,
    "Camera-to-finger distance along the optical axis (to the finger's nearest point), metres "
    "(metric scale of depth: its nearest point is put there)",
    min_value=0.005, max_value=2.0)
