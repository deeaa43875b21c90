"""The calibration in force, and how a new one comes into force (calib_node's core).

`CalibrationKeeper` holds the light calibration and the flat field in force. A new one is
made from `Shots` (the images and the camera_info of one burst, as arrays), checked
(request, image sizes, ``calibration_store.lights_problems`` / ``flat_field_problems``),
and only then put in force: handed to the ``publish_*`` callbacks, saved to the
calibration directory (``calibration_store``) with its picture (``calibration_picture``).
A refused one changes nothing (a refused light calibration's picture is saved as
``lights_rejected.png``). A light calibration with ``add_placement`` is combined with the
placements of the one in force (``led_triangulation.combine_placements``).

No ROS here: calib_node converts the messages and passes the parameters as
`CalibrationSettings`; every answer is a `CalibrationAnswer` with the message the service
returns, and the keeper logs what calib_node logs.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from fingerps_calib.calibration_camera import (
    CalibrationCamera,
    DriverCameraInfo,
    calibration_camera,
    camera_image_size,
    check_camera_size,
    check_frame_size,
    check_min_size,
)
from fingerps_calib.calibration_picture import flat_field_picture, write_png
from fingerps_calib.calibration_report import (
    light_calibration_picture,
    lights_lines,
    lights_summary,
)
from fingerps_calib.calibration_store import (
    FLAT_FIELD_FILE,
    LIGHTS_FILE,
    FlatFieldRecord,
    LightsRecord,
    flat_field_problems,
    iso_date,
    lights_problems,
    load_flat_field,
    load_lights,
    save_flat_field,
    save_lights,
)
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics
from fingerps_calib.lights.led_triangulation import Placement, combine_placements
from fingerps_calib.lights.sphere_calibration import LightCalibrationResult, calibrate_lights
from fingerps_calib.lights.sphere_silhouette import RADIUS_RANGE_M, check_radius
from fingerps_recon.photometric.full_scale import MONO16_DEFAULT
from fingerps_ros.log import Log

DEFAULT_FRAME_ID = "fingerps_camera_optical_frame"
LIGHTS_PICTURE = "lights.png"
REFUSED_LIGHTS_PICTURE = "lights_rejected.png"
FLAT_FIELD_PICTURE = "flat_field.png"



@dataclass(frozen=True)
class CalibrationSettings:
    """calib_node's parameters a calibration uses (the defaults are the parameters').

    Attributes
    ----------
    camera_name : str
        Written into calibrations; a saved calibration of another camera is not loaded.
    sphere_radius_m : float
        Used when a request gives 0.
    reference_point_optical_m : (3,) float
        Where the finger rests; the directions of two or more placements start there.
    sphere_distance_tolerance : float
        Fraction of the reference point's distance the sphere centre may be off by.
    flat_field_degree : int
        Degree of the polynomial fitted to each white-target image.
    mono16_full_scale : float
        Largest value of a mono16 image.
    """

    camera_name: str = "fingerps_sim"
    sphere_radius_m: float = 0.004
    reference_point_optical_m: tuple[float, float, float] = (0.0, 0.0025, 0.09)
    sphere_distance_tolerance: float = 0.3
    flat_field_degree: int = 4
    mono16_full_scale: float = MONO16_DEFAULT


@dataclass(frozen=True, eq=False)
class Shots:
    """One burst to calibrate from.

    Attributes
    ----------
    images : (K, H, W)
        One image a LED, in LED order (mono8, mono16 or 32FC1 values).
    encoding : str
        The images' encoding (``mono8``: full scale 255, ``mono16``: the setting).
    frame_id : str
        The first frame's frame id ('' when unset).
    dark : (H, W) or None
        The all-LEDs-off frame, when there is one.
    camera_info : DriverCameraInfo or None
        The driver's camera_info, when known.
    """

    images: np.ndarray
    encoding: str
    frame_id: str = ""
    dark: np.ndarray | None = None
    camera_info: DriverCameraInfo | None = None


@dataclass(frozen=True, eq=False)
class CalibrationAnswer:
    """A service's answer: success, the message, and what was put in force.

    Attributes
    ----------
    success : bool
    message : str
        The service response's message (a refusal says why and what to do).
    lights : LightsRecord or None
        The light calibration put in force.
    relative_intensities : tuple of float
        Its relative intensities (from the flat field in force, else ones).
    flat : FlatFieldRecord or None
        The flat field put in force.
    """

    success: bool
    message: str
    lights: LightsRecord | None = None
    relative_intensities: tuple[float, ...] = ()
    flat: FlatFieldRecord | None = None


class _RefusedError(FingerpsCalibError):
    """A calibration that failed its checks, with the list of problems."""

    def __init__(self, message: str, problems: tuple[str, ...]) -> None:
        super().__init__(message)
        self.problems = problems


def open_calibration_dir(directory: str) -> Path | None:
    """The calibration directory, made if missing; None for '' (neither save nor load).

    Raises
    ------
    FingerpsCalibError
        It cannot be made or is not writable.
    """
    if not directory:
        return None
    path = Path(directory).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        writable = os.access(path, os.W_OK)
    except OSError as exc:
        writable, reason = False, str(exc)
    else:
        reason = "not writable"
    if not writable:
        raise FingerpsCalibError(
            f"calibration_dir {path}: {reason}; set calibration_dir to a "
            "writable directory (or to '' to neither save nor load calibrations)")
    return path


_Record = TypeVar("_Record", LightsRecord, FlatFieldRecord)


def _ignore(*_: object) -> None:
    return None


class CalibrationKeeper:
    """Keeps the calibration in force: makes, checks, saves and loads calibrations.

    Parameters
    ----------
    directory : Path or None
        Where calibrations are saved and loaded from (`open_calibration_dir`); None: neither.
    file_camera : CameraIntrinsics or None
        The intrinsics of ``camera_info_file``; None: the driver's camera_info.
    log : Log
    now_ns : callable
        The time, ns since the epoch (the stamp of a new calibration).
    publish_lights : callable(LightsRecord, list of float)
        Called with a light calibration (and its relative intensities) put in force.
    publish_flat : callable(FlatFieldRecord)
        Called with a flat field put in force.
    """

    def __init__(self, directory: Path | None, *, file_camera: CameraIntrinsics | None,
                 log: Log, now_ns: Callable[[], int],
                 publish_lights: Callable[[LightsRecord, list[float]], object] = _ignore,
                 publish_flat: Callable[[FlatFieldRecord], object] = _ignore) -> None:
        self._dir = directory
        self._file_camera = file_camera
        self._lights: LightsRecord | None = None
        self._flat: FlatFieldRecord | None = None
        self._publish_lights, self._publish_flat = publish_lights, publish_flat
        self._log, self._now_ns = log, now_ns

    @property
    def lights(self) -> LightsRecord | None:
        """The light calibration in force."""
        return self._lights

    @property
    def flat(self) -> FlatFieldRecord | None:
        """The flat field in force."""
        return self._flat

    def in_force(self) -> str:
        """'in force: lights of <date>, flat field of <date>' (or 'no lights', ...)."""
        lights = f"lights of {self._lights.date}" if self._lights is not None else "no lights"
        flat = (f"flat field of {self._flat.date}" if self._flat is not None
                else "no flat field")
        return f"in force: {lights}, {flat}"

    def intensities(self, count: int) -> list[float]:
        """Relative intensities of ``count`` LEDs: the flat field's if it has as many."""
        if self._flat is not None and len(self._flat.relative_intensities) == count:
            return [float(x) for x in self._flat.relative_intensities]
        return [1.0] * count

    # ------------------------------------------------------------------ saved calibration
    def load_saved(self, camera_name: str) -> None:
        """Load and publish the saved calibration of ``camera_name``, if any (errors are
        logged, not raised: the operator can recalibrate, which replaces the files)."""
        if self._dir is None:
            return
        flat = self._load_checked("flat field", load_flat_field, lambda f: flat_field_problems(
            f.portions, f.relative_intensities), camera_name)
        if flat is not None:
            self._flat = flat
            self._publish_flat(flat)
            self._log.info(
                f"loaded the flat field of {flat.date} ({flat.portions.shape[0]} maps "
                f"{flat.portions.shape[2]}x{flat.portions.shape[1]}) from "
                f"{self._dir / FLAT_FIELD_FILE}; published")
        lights = self._load_checked("light calibration", load_lights, lambda r: lights_problems(
            r.lights.directions_optical, self.intensities(r.lights.led_count),
            led_positions_optical_m=r.lights.led_positions_optical_m), camera_name)
        if lights is not None:
            self._lights = lights
            self._publish_lights(lights, self.intensities(lights.lights.led_count))
            self._log.info(
                f"loaded the light calibration of {lights.date} ({lights.lights.led_count} "
                f"LEDs, {len(lights.lights.placements)} placement(s)) from "
                f"{self._dir / LIGHTS_FILE}; published")

    def _load_checked(self, what: str, load: Callable[[Path], _Record | None],
                      problems: Callable[[_Record], list[str]],
                      camera_name: str) -> _Record | None:
        """The saved ``what`` if it loads, passes its checks and is of ``camera_name``
        (``load_saved``: only with a calibration directory)."""
        assert self._dir is not None
        try:
            record = load(self._dir)
        except FingerpsCalibError as exc:
            self._log.error(f"saved {what} not loaded: {exc}")
            return None
        if record is None:
            return None
        if found := problems(record):
            self._log.error(f"saved {what} in {self._dir} not loaded: {'; '.join(found)}; "
                            "recalibrate")
            return None
        if record.camera_name != camera_name:
            self._log.warning(
                f"saved {what} in {self._dir} is for camera {record.camera_name!r}, this "
                f"node's camera_name is {camera_name!r}: not loaded; recalibrate")
            return None
        return record

    # ------------------------------------------------------------------ lights
    def calibrate_lights(self, shots: Callable[[], Shots], *, sphere_radius_m: float,
                         add_placement: bool, settings: CalibrationSettings
                         ) -> CalibrationAnswer:
        """Calibrate the light directions from a shiny sphere and put them in force.

        Parameters
        ----------
        shots : callable
            Returns the sphere's burst; called once the request's radius is checked (it
            may capture one). A `FingerpsCalibError` it raises refuses the call.
        sphere_radius_m : float
            The request's radius; 0: ``settings.sphere_radius_m``.
        add_placement : bool
            Combine with the placements of the calibration in force.
        settings : CalibrationSettings

        Returns
        -------
        CalibrationAnswer
            With ``lights`` and ``relative_intensities`` when put in force.
        """
        radius = sphere_radius_m or settings.sphere_radius_m
        images: np.ndarray | None = None
        result: LightCalibrationResult | None = None
        camera: CalibrationCamera | None = None
        try:
            _check_request_radius(radius, settings.sphere_radius_m)
            taken = shots()
            images, info = taken.images, taken.camera_info
            camera = calibration_camera(self._file_camera, info)
            if camera is None:
                raise FingerpsCalibError(
                    ("no camera intrinsics: start driver_node (its camera_info)"
                     if info is None else
                     "the driver's camera_info has no intrinsics (K = 0): set the driver's")
                    + " or calib_node's camera_info_file (make one with `ros2 run "
                    "fingerps_calib calibrate_camera` from checkerboard images)")
            check_min_size(images)
            check_camera_size(images, camera)
            reference = np.asarray(settings.reference_point_optical_m, dtype=float)
            tolerance = settings.sphere_distance_tolerance
            distance = float(np.linalg.norm(reference))
            result = calibrate_lights(
                images, camera_matrix=camera.matrix, radius_m=radius,
                distortion=camera.distortion,
                saturation_level=_full_scale(taken.encoding, settings),
                require_whole_sphere=True,
                expected_distance_m=(distance * (1 - tolerance), distance * (1 + tolerance)))
            if not result.ok:
                raise _RefusedError("light calibration failed its checks: "
                                    + "; ".join(result.problems), result.problems)
            placements = [Placement.from_result(result)]
            if add_placement and self._lights is not None:
                _check_compatible(self._lights, images, camera.matrix)
                placements = [*self._lights.lights.placements, *placements]
            combined = combine_placements(placements, reference_point_optical_m=reference)
            if not combined.ok:
                raise _RefusedError(
                    f"the {len(placements)} sphere placements do not combine (this placement "
                    "is not added): " + "; ".join(combined.problems), combined.problems)
            frame_id = (info.frame_id if info is not None and info.frame_id
                        else taken.frame_id or DEFAULT_FRAME_ID)
            h, w = images.shape[1:]
            record = LightsRecord(
                camera_name=settings.camera_name, frame_id=frame_id,
                stamp_ns=self._now_ns(), image_width=w, image_height=h,
                camera_matrix=camera.matrix, lights=combined)
            intensities = self.intensities(combined.led_count)
            problems = tuple(lights_problems(
                combined.directions_optical, intensities,
                led_positions_optical_m=combined.led_positions_optical_m))
            if problems:
                raise _RefusedError("the light calibration is not usable (not put in force): "
                                    + "; ".join(problems), problems)
        except _RefusedError as exc:
            return self._refuse_lights(str(exc), exc.problems, images, result, camera,
                                       settings)
        except FingerpsCalibError as exc:
            return self._refuse_lights(str(exc), (str(exc),), images, result, camera,
                                       settings)
        self._lights = record
        self._publish_lights(record, intensities)
        message = lights_summary(record) + self._save_lights(record, images, result, camera)
        self._log.info(message)
        return CalibrationAnswer(True, message, lights=record,
                                 relative_intensities=tuple(intensities))

    def _refuse_lights(self, message: str, problems: tuple[str, ...],
                       images: np.ndarray | None, result: LightCalibrationResult | None,
                       camera: CalibrationCamera | None,
                       settings: CalibrationSettings) -> CalibrationAnswer:
        if self._lights is not None:
            message += f" [the calibration of {self._lights.date} stays in force]"
        if images is not None and result is not None and camera is not None \
                and self._dir is not None:
            try:
                picture = light_calibration_picture(
                    images, result, camera, result.directions_optical, [],
                    title="light calibration REFUSED",
                    lines=[f"camera {settings.camera_name}, {iso_date(self._now_ns())}"],
                    problems=problems)
                path = write_png(self._dir / REFUSED_LIGHTS_PICTURE, picture)
                message += f" [picture: {path}]"
            except FingerpsCalibError as exc:
                self._log.warning(f"no picture of the refused calibration: {exc}")
        self._log.error(f"light calibration refused: {message}")
        return CalibrationAnswer(False, message)

    def _save_lights(self, record: LightsRecord, images: np.ndarray,
                     result: LightCalibrationResult, camera: CalibrationCamera) -> str:
        def picture() -> np.ndarray:
            placements = record.lights.placements
            return light_calibration_picture(
                images, result, camera, record.lights.directions_optical,
                [pl.directions_optical for pl in placements] if len(placements) > 1 else [],
                title="light calibration in force", lines=lights_lines(record))
        return self._save("light calibration", lambda d: save_lights(d, record),
                          picture, LIGHTS_PICTURE)

    def _save(self, what: str, save: Callable[[Path], Path],
              picture: Callable[[], np.ndarray], picture_name: str) -> str:
        """Save a calibration put in force and its picture; returns what the answer adds."""
        if self._dir is None:
            return "; not saved (calibration_dir is empty)"
        try:
            path = save(self._dir)
        except FingerpsCalibError as exc:
            self._log.error(f"{what} in force but NOT SAVED: {exc}")
            return f"; NOT SAVED: {exc}"
        text = f"; saved to {path}"
        try:
            text += f"; picture {write_png(self._dir / picture_name, picture())}"
        except FingerpsCalibError as exc:
            self._log.warning(f"no picture of the {what}: {exc}")
        return text

    # ------------------------------------------------------------------ flat field
    def calibrate_flat_field(self, shots: Callable[[], Shots], *,
                             settings: CalibrationSettings) -> CalibrationAnswer:
        """Make the flat-field maps from a white target and put them in force.

        A light calibration in force with as many LEDs is handed to ``publish_lights``
        again, with the new relative intensities.

        Parameters
        ----------
        shots : callable
            Returns the white target's burst (with a dark frame, if any).
        settings : CalibrationSettings

        Returns
        -------
        CalibrationAnswer
            With ``flat`` when put in force.
        """
        degree = settings.flat_field_degree
        try:
            taken = shots()
            images, dark = taken.images, taken.dark
            check_min_size(images)
            size = camera_image_size(self._file_camera, taken.camera_info)
            check_frame_size(images, size)
            if dark is not None and dark.shape != images.shape[1:]:
                raise FingerpsCalibError(
                    f"the dark frame is {dark.shape[1]}x{dark.shape[0]}, the images "
                    f"{images.shape[2]}x{images.shape[1]}; recapture")
            result = flat_field_maps(images, dark=dark,
                                     saturation_level=_full_scale(taken.encoding, settings),
                                     polynomial_degree=degree)
            problems = flat_field_problems(
                result.portions, result.relative_intensities,
                image_size=size[:2] if size is not None else None)
            if problems:
                raise FingerpsCalibError("the flat field is not usable (not put in force): "
                                         + "; ".join(problems))
        except FingerpsCalibError as exc:
            message = str(exc)
            if self._flat is not None:
                message += f" [the flat field of {self._flat.date} stays in force]"
            self._log.error(f"flat-field calibration refused: {message}")
            return CalibrationAnswer(False, message)
        record = FlatFieldRecord(
            camera_name=settings.camera_name, frame_id=taken.frame_id or DEFAULT_FRAME_ID,
            stamp_ns=self._now_ns(), portions=result.portions,
            relative_intensities=result.relative_intensities,
            fit_residuals=result.fit_residuals, polynomial_degree=degree)
        self._flat = record
        self._publish_flat(record)
        count = len(images)
        if self._lights is not None and self._lights.lights.led_count == count:
            self._publish_lights(self._lights, self.intensities(count))
        message = (
            f"{count} flat-field maps; relative intensities "
            + ", ".join(f"{x:.2f}" for x in result.relative_intensities)
            + "; fit residual max " + f"{100 * np.max(result.fit_residuals):.2f}%"
            + self._save_flat(record))
        self._log.info(message)
        return CalibrationAnswer(True, message, flat=record)

    def _save_flat(self, record: FlatFieldRecord) -> str:
        def picture() -> np.ndarray:
            return flat_field_picture(
                record.portions, relative_intensities=record.relative_intensities,
                fit_residuals=record.fit_residuals, title="flat field in force",
                lines=[f"camera {record.camera_name}, {record.date}; polynomial degree "
                       f"{record.polynomial_degree}"])
        return self._save("flat field", lambda d: save_flat_field(d, record), picture,
                          FLAT_FIELD_PICTURE)

def _check_request_radius(radius: float, default_m: float) -> None:
    """Refuse a request's sphere radius outside `RADIUS_RANGE_M`."""
    try:
        check_radius(radius)
    except FingerpsCalibError:
        lo, hi = RADIUS_RANGE_M
        raise FingerpsCalibError(
            f"sphere_radius {radius!r} m in the request: the radius of a calibration "
            f"sphere must be finite and between {lo:g} and {hi:g} m "
            f"({1e3 * lo:g}-{1e3 * hi:g} mm); give the sphere's radius in metres "
            "(0.004 for a ball of 8 mm), or 0 for calib_node's sphere_radius "
            f"({default_m:g} m)") from None


def _check_compatible(in_force: LightsRecord, images: np.ndarray,
                      camera_matrix: np.ndarray) -> None:
    """Refuse adding a placement of another LED count, image size or camera matrix."""
    restart = "calibrate with add_placement=false to start a new set of placements"
    n_led, h, w = images.shape
    if in_force.lights.led_count != n_led:
        raise FingerpsCalibError(
            f"add_placement: the calibration in force has {in_force.lights.led_count} "
            f"LEDs, these images {n_led}; {restart}")
    if (in_force.image_width, in_force.image_height) != (w, h) or not np.allclose(
            in_force.camera_matrix, camera_matrix, rtol=1e-9, atol=1e-9):
        raise FingerpsCalibError(
            "add_placement: the camera (image size or intrinsics) differs from the "
            f"calibration in force's; {restart}")


def _full_scale(encoding: str, settings: CalibrationSettings) -> float | None:
    """The saturation level of images of ``encoding`` (None: no known full scale)."""
    if encoding == "mono8":
        return 255.0
    if encoding == "mono16":
        return float(settings.mono16_full_scale)
    return None
