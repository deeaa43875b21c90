"""The largest grey level of a burst's images, by encoding, and the nodes' parameter for it.

A leaf module (no numba, no solver): calib_node, scan_node and recon_node declare
``mono16_full_scale`` from it without loading the reconstruction pipeline.
"""

from __future__ import annotations

from fingerps_ros.parameter_table import ParameterRow, check_finite

FULL_SCALE = {"mono8": 255.0, "mono16": 4095.0}
"""Largest grey level of each image encoding a burst may have (mono16: 12-bit sensors, the
default of the nodes' ``mono16_full_scale``)."""

MONO16_DEFAULT = FULL_SCALE["mono16"]


def full_scale_of(encoding: str, *, mono16_full_scale: float = MONO16_DEFAULT) -> float:
    """The ``full_scale`` to reconstruct images of ``encoding`` with: ``mono16_full_scale``
    for mono16, else the encoding's `FULL_SCALE` (255 for an encoding not listed)."""
    return mono16_full_scale if encoding == "mono16" else FULL_SCALE.get(encoding, 255.0)


MONO16_FULL_SCALE = ParameterRow(
    "mono16_full_scale", MONO16_DEFAULT,
    "Largest value of a mono16 image (4095 for 12-bit sensors)", min_value=1.0,
    max_value=65535.0, check=check_finite)
"""The ``mono16_full_scale`` parameter of every node that reads mono16 images (recon_node,
scan_node, calib_node): one row of their tables (``fingerps_ros.parameter_table``)."""
