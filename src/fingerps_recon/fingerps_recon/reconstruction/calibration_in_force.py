"""The calibration in force for reconstruction, one object shared by recon_node's worker and
scan_node: the light calibration and the flat-field maps, each checked when it arrives (a
refused one leaves the previous one in force, and its reason is kept until one of its kind
is accepted), and the calibration prepared for the bursts' camera.

Whether a flat field fits a burst is decided here alone (:meth:`CalibrationInForce.flat_for`):
maps of another size or LED count are not used (the burst is reconstructed without them, and
the caller says so).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from fingerps_msgs.msg import FlatField, LightCalibration
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.pipeline import (
    PreparedCalibration,
    ReconstructionOptions,
    prepare_calibration,
)
from fingerps_recon.reconstruction.burst_intake import (
    BurstLimits,
    calibration_arrays,
    check_light_calibration,
    flat_field_maps,
)

_T = TypeVar("_T")

LIGHTS = "light calibration"
FLAT_FIELD = "flat field"


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


class CalibrationInForce:
    """The light calibration and flat-field maps the next bursts are reconstructed with,
    and the calibration prepared from them (:class:`PreparedCalibrations`)."""

    def __init__(self) -> None:
        self.lights: LightCalibration | None = None
        self.flat_maps: np.ndarray | None = None  # (K, H, W) float32 portion maps
        self.prepared = PreparedCalibrations()
        self.refused: dict[str, str] = {}  # kind (LIGHTS, FLAT_FIELD) -> why it was refused
        self.refused_count = 0

    def offer_lights(self, msg: LightCalibration) -> LightCalibration:
        """Put a light calibration in force if it can determine normals
        (``burst_intake.check_light_calibration``); else raise its ``FingerpsReconError``,
        counted and kept as the reason, the previous calibration staying in force."""
        self.lights = self._checked(LIGHTS, lambda: check_light_calibration(msg))
        return self.lights

    def offer_flat(self, msg: FlatField, limits: BurstLimits) -> np.ndarray:
        """Put a flat field's maps in force if they are usable
        (``burst_intake.flat_field_maps``); else raise as :meth:`offer_lights`."""
        self.flat_maps = self._checked(FLAT_FIELD, lambda: flat_field_maps(msg, limits))
        return self.flat_maps

    def _checked(self, kind: str, check: Callable[[], _T]) -> _T:
        try:
            result = check()
        except FingerpsReconError as exc:
            self.refused_count += 1
            self.refused[kind] = str(exc)
            raise
        self.refused.pop(kind, None)
        return result

    def require_lights(self) -> LightCalibration:
        """The light calibration in force, or ``FingerpsReconError`` saying how to get one
        (and why the last one was refused, if it was)."""
        if self.lights is None:
            refused = self.refused.get(LIGHTS)
            raise FingerpsReconError(
                "no light calibration yet"
                + (f" (the last one was refused: {refused})" if refused else "")
                + ": call the calibrate_lights service (or start calib_node with a saved "
                "calibration) before sending bursts")
        return self.lights

    def flat_for(self, shape: tuple[int, ...]) -> np.ndarray | None:
        """The flat-field maps in force if they fit images of ``shape`` (K, H, W): one map per
        image, of the images' size; else None (the images are used without a flat field)."""
        maps = self.flat_maps
        return maps if maps is not None and maps.shape == tuple(shape) else None

    def prepare(self, lights: LightCalibration, camera_matrix: np.ndarray,
                shape: tuple[int, int], options: ReconstructionOptions
                ) -> tuple[PreparedCalibration, bool]:
        """``lights`` (the calibration in force, read once by the caller) prepared for a
        camera (``camera_matrix``, image ``shape`` (H, W)) with the flat field where it fits
        (:meth:`flat_for`), kept from the last call when nothing changed
        (:class:`PreparedCalibrations`); and whether the flat field was used."""
        maps = self.flat_for((len(lights.directions), *shape))
        return self.prepared.get(lights, maps, camera_matrix, shape, options), maps is not None
