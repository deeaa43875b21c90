"""One Burst message reconstructed with the calibration in force
(:class:`~fingerps_recon.reconstruction.calibration_in_force.CalibrationInForce`), prepared
once for the bursts' camera and kept for the next burst.

Used by recon_node's worker and by scan_node. Every burst or calibration that cannot be
reconstructed ends in a ``FingerpsReconError``, an empty result too
(:class:`EmptyReconstructionError`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from fingerps_msgs.msg import Burst
from fingerps_recon.errors import EmptyReconstructionError
from fingerps_recon.photometric.full_scale import MONO16_DEFAULT
from fingerps_recon.photometric.pipeline import (
    Reconstruction,
    ReconstructionOptions,
    reconstruct_prepared,
)
from fingerps_recon.reconstruction.burst_intake import BurstLimits, burst_inputs
from fingerps_recon.reconstruction.calibration_in_force import CalibrationInForce
from fingerps_recon.surface.rolled_print import RolledPrint, rolled_print


@dataclass(frozen=True)
class BurstReconstruction:
    """What :func:`reconstruct_burst` used and made."""

    result: Reconstruction
    images: np.ndarray            # (K, H, W) in LED order, as captured
    dark: np.ndarray | None       # (H, W) the burst's dark frame
    full_scale: float
    flat_field_used: bool
    camera_matrix: np.ndarray     # (3, 3) K of the burst's camera_info

    def fingerprint(self) -> RolledPrint:
        """The rolled-equivalent 500 ppi print of this reconstruction
        (`fingerps_recon.surface.rolled_print`); raises `RolledPrintError` with the reason when the
        reconstruction covers too little of the finger or is too noisy or strained."""
        result = self.result
        return rolled_print(result.depth_m, mask=result.mask, camera_matrix=self.camera_matrix,
                            normals_ps=result.normals_ps)


def reconstruct_burst(burst: Burst, calibration: CalibrationInForce, *,
                      options: ReconstructionOptions, mono16_full_scale: float = MONO16_DEFAULT,
                      limits: BurstLimits | None = None) -> BurstReconstruction:
    """Reconstruct a Burst message with the calibration in force (its flat field where it
    fits the images, :meth:`CalibrationInForce.flat_for`), prepared once for the bursts'
    camera and kept there for the next burst; raises ``FingerpsReconError`` on any burst or
    calibration it cannot reconstruct: no light calibration, beyond ``limits``, malformed
    (``burst_intake.burst_inputs``), a degenerate calibration
    (``pipeline.check_calibration``), or an empty result (:class:`EmptyReconstructionError`).
    """
    lights = calibration.require_lights()
    inputs = burst_inputs(burst, len(lights.directions), mono16_full_scale=mono16_full_scale,
                          limits=limits)
    images = inputs.images
    start = time.perf_counter()
    cache = calibration.prepared
    count = cache.count
    prepared, flat_used = calibration.prepare(lights, inputs.camera_matrix, images.shape[1:],
                                              options)
    result = reconstruct_prepared(images, prepared, full_scale=inputs.full_scale,
                                  dark=inputs.dark, options=options,
                                  hk_initial_scale=cache.hk_scale)
    if result.hk_scale is not None and math.isfinite(result.hk_scale):
        cache.hk_scale = result.hk_scale  # where the next burst holds A
    if cache.count != count:  # prepared for this burst: say what it cost
        result.timings_ms["calibration"] = cache.seconds * 1e3
    result.timings_ms["total"] = (time.perf_counter() - start) * 1e3
    if not result.mask.any() or len(result.points_optical) == 0:
        raise EmptyReconstructionError(
            f"nothing reconstructed: {int(result.mask.sum())} pixels with a valid normal, "
            f"{len(result.points_optical)} points although the mask found a finger; check "
            "the light calibration (recalibrate the lights and the flat field)")
    return BurstReconstruction(result, images, inputs.dark, inputs.full_scale,
                               flat_used, inputs.camera_matrix)
