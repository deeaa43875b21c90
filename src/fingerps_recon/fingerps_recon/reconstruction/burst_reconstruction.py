"""One Burst message reconstructed with the calibration in force, the calibration prepared
once for the bursts' camera (:class:`PreparedCalibrations`) and kept for the next burst.

Used by recon_node's worker and by scan_node. Every burst or calibration that cannot be
reconstructed ends in a ``FingerpsReconError``, an empty result too
(:class:`EmptyReconstructionError`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon.errors import EmptyReconstructionError
from fingerps_recon.photometric.full_scale import MONO16_DEFAULT
from fingerps_recon.photometric.pipeline import (
    PreparedCalibration,
    Reconstruction,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.reconstruction.burst_intake import (
    BurstLimits,
    burst_inputs,
    calibration_arrays,
)
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


class PreparedCalibrations:
    """The calibration prepared for the bursts' camera (``prepare_calibration``): kept while
    the light calibration, the flat field, the camera matrix, the image size, the working
    distance, the projection and the model stay the same; prepared again when one changes.
    With it the HK model's global scale A refitted at the last burst's solution
    (``hk_scale``), at which the next burst holds A (A depends on the skin and the LEDs'
    power, not on the pose; ``reconstruct_prepared(hk_initial_scale=...)``)."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._held: tuple = ()  # the key's objects, kept alive so their ids stay theirs
        self._prepared: PreparedCalibration | None = None
        self.count = 0  # calibrations prepared so far
        self.seconds = 0.0  # time the last preparation took
        self.hk_scale: float | None = None  # the HK model's A refitted at the last burst

    def get(self, lights: LightCalibration, flat_maps: np.ndarray | None,
            camera_matrix: np.ndarray, shape: tuple[int, int],
            options: ReconstructionOptions) -> PreparedCalibration:
        """The prepared calibration for these inputs, prepared now if they changed."""
        key = (id(lights), id(flat_maps), camera_matrix.tobytes(), tuple(shape),
               options.working_distance_m, options.projection, options.model)
        if key != self._key or self._prepared is None:
            start = time.perf_counter()
            directions, intensities, leds = calibration_arrays(lights)
            self._prepared = prepare_calibration(
                directions, camera_matrix=camera_matrix, shape=shape,
                intensities=intensities, portions=flat_maps, led_positions_optical=leds,
                options=options)
            self._key, self._held = key, (lights, flat_maps)
            self.hk_scale = None
            self.count += 1
            self.seconds = time.perf_counter() - start
        return self._prepared


def reconstruct_burst(burst: Burst, lights: LightCalibration, flat_maps: np.ndarray | None,
                      *, options: ReconstructionOptions, mono16_full_scale: float = MONO16_DEFAULT,
                      prepared: PreparedCalibrations | None = None,
                      limits: BurstLimits | None = None) -> BurstReconstruction:
    """Reconstruct a Burst message with a light calibration and flat-field maps (K, H, W)
    (None, or maps of another shape: not used), the calibration prepared by ``prepared``
    (kept there for the next burst) or afresh; raises ``FingerpsReconError`` on any burst or
    calibration it cannot reconstruct: beyond ``limits``, malformed
    (``burst_intake.burst_inputs``), a degenerate calibration
    (``pipeline.check_calibration``), or an empty result (:class:`EmptyReconstructionError`).
    """
    inputs = burst_inputs(burst, len(lights.directions), mono16_full_scale=mono16_full_scale,
                          limits=limits)
    images = inputs.images
    maps = flat_maps if flat_maps is not None and flat_maps.shape == images.shape else None
    start = time.perf_counter()
    cache = prepared or PreparedCalibrations()
    count = cache.count
    calibration = cache.get(lights, maps, inputs.camera_matrix, images.shape[1:], options)
    result = reconstruct_prepared(images, calibration, full_scale=inputs.full_scale,
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
                               maps is not None, inputs.camera_matrix)
