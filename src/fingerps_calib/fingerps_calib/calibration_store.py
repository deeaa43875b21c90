"""The calibration in force, saved to a directory and loaded from it (YAML + npz).

Files in the calibration directory (calib_node's ``calibration_dir``):

- ``lights.yaml``: the light calibration, human-readable: camera, date, method, the
  directions (optical and PS frame), per-LED residuals, the sphere placements (centre,
  silhouette residual, highlights, mirror rays) and, from two or more placements, the
  triangulated LED positions and the reference point of the directions.
- ``flat_field.yaml``: the flat field's metadata: camera, date, image size, relative
  intensities, fit residuals, and the name and SHA-256 of its maps file.
- ``flat_field_<UTC time>.npz``: the maps, one (K, H, W) float32 array ``portions``
  (numpy's compressed npz). A new flat field writes a new maps file, then replaces
  flat_field.yaml, then deletes the maps files no longer named, so whenever a crash
  happens flat_field.yaml names a complete maps file.

Every file is written under a temporary name in the same directory, flushed to disk, and
renamed over the old one (atomic on POSIX): a crash or a full disk never leaves a
half-written calibration. calib_node writes only calibrations that passed their checks.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.led_triangulation import CombinedLights, Placement, TriangulatedLights
from fingerps_recon.photometric.frames import optical_to_ps

LIGHTS_FILE = "lights.yaml"
FLAT_FIELD_FILE = "flat_field.yaml"
LIGHTS_FORMAT = "fingerps_light_calibration/1"
FLAT_FIELD_FORMAT = "fingerps_flat_field/1"
_MAPS_PATTERN = re.compile(r"^flat_field_\d{8}T\d{6}_\d{9}Z\.npz$")

_LIGHTS_HEADER = """\
# fingerps light calibration (paper Sec. 3.1), written by fingerps_calib.
# direction: unit vector from the scene towards each LED in the camera optical frame
# (x right, y down, z forward); direction_ps: the same in the photometric-stereo frame
# (x right, y up, z towards the camera). Positions in metres, optical frame.
# highlight_residual_px: how far the highlight centroid moves with the threshold;
# edge_rms_px: rms distance of the sphere's silhouette points from the fitted sphere;
# position_residual_mm: rms distance of the triangulated LED from its rays.
"""
_FLAT_HEADER = """\
# fingerps flat field (paper Eq. 11), written by fingerps_calib. The maps p_k are in
# maps_file (numpy npz, array 'portions', K x height x width float32).
# fit_residual_pct: rms departure of each white-target image from its smooth field.
"""


@dataclass(frozen=True, eq=False)
class CalibrationStamp:
    """Which camera a saved calibration is for and when it was made (the first fields of
    `LightsRecord` and `FlatFieldRecord`).

    Attributes
    ----------
    camera_name, frame_id : str
    stamp_ns : int
        When the calibration was made, ns since the epoch (UTC).
    """

    camera_name: str
    frame_id: str
    stamp_ns: int

    @property
    def date(self) -> str:
        """``stamp_ns`` as an ISO 8601 UTC date, e.g. ``2025-05-01T09:30:12Z``."""
        return iso_date(self.stamp_ns)


@dataclass(frozen=True, eq=False)
class LightsRecord(CalibrationStamp):
    """A light calibration with the camera, time (`CalibrationStamp`) and intrinsics it was
    made with.

    Attributes
    ----------
    image_width, image_height : int
    camera_matrix : (3, 3) float64
        Intrinsics the calibration used.
    lights : CombinedLights
    """

    image_width: int
    image_height: int
    camera_matrix: np.ndarray
    lights: CombinedLights


@dataclass(frozen=True, eq=False)
class FlatFieldRecord(CalibrationStamp):
    """A flat field with the camera and time it was made with (`CalibrationStamp`).

    Attributes
    ----------
    portions : (K, H, W) float32
    relative_intensities : (K,) float64
    fit_residuals : (K,) float64
        `FlatFieldResult.fit_residuals`.
    polynomial_degree : int
    """

    portions: np.ndarray
    relative_intensities: np.ndarray
    fit_residuals: np.ndarray
    polynomial_degree: int


def iso_date(stamp_ns: int) -> str:
    """ISO 8601 UTC date of a time in ns since the epoch, to the second."""
    moment = datetime.fromtimestamp(stamp_ns / 1e9, tz=UTC)
    return moment.isoformat(timespec="seconds").replace("+00:00", "Z")


# -------------------------------------------------------------------------- validation

#: Directions closer than this (degrees) to each other all count as one direction: a light
#: calibration whose directions are all parallel cannot separate shading from albedo.
MIN_DIRECTION_SPREAD_DEG = 1.0


def lights_problems(
    directions_optical: np.ndarray,
    relative_intensities: np.ndarray,
    *,
    led_positions_optical_m: np.ndarray | None = None,
) -> list[str]:
    """What makes a light calibration unusable; empty if it may be put in force.

    Parameters
    ----------
    directions_optical : (K, 3) float
        Light directions, optical frame: each finite and of unit length, not all parallel
        (within `MIN_DIRECTION_SPREAD_DEG`).
    relative_intensities : (K,) float
        Each finite and > 0.
    led_positions_optical_m : (K, 3) float, optional
        Triangulated LED positions (metres), each finite.

    Returns
    -------
    list of str
        One sentence a problem.
    """
    d = np.asarray(directions_optical, dtype=np.float64)
    e = np.asarray(relative_intensities, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) < 1:
        return [f"directions have shape {d.shape}, expected (K, 3) with K >= 1"]
    problems = []
    n_led = len(d)
    norms = np.linalg.norm(d, axis=1)
    bad = np.flatnonzero(~np.isfinite(norms) | (np.abs(norms - 1.0) > 1e-6))
    if len(bad):
        problems.append("the directions of LED(s) " + ", ".join(map(str, bad))
                        + " are not finite unit vectors")
    elif n_led > 1:
        spread = np.degrees(np.arccos(np.clip(d @ d[0], -1.0, 1.0)))
        if np.max(spread) < MIN_DIRECTION_SPREAD_DEG:
            problems.append(f"all {n_led} directions are parallel (within "
                            f"{np.max(spread):.2g} deg): photometric stereo needs lights "
                            "from different directions")
    if e.shape != (n_led,):
        problems.append(f"{e.size} relative intensities for {n_led} LEDs")
    elif not np.all(np.isfinite(e) & (e > 0)):
        bad = np.flatnonzero(~(np.isfinite(e) & (e > 0)))
        problems.append("the relative intensities of LED(s) " + ", ".join(map(str, bad))
                        + " are not finite and > 0")
    if led_positions_optical_m is not None:
        q = np.asarray(led_positions_optical_m, dtype=np.float64)
        if q.size and (q.shape != (n_led, 3) or not np.all(np.isfinite(q))):
            problems.append(f"the LED positions (shape {q.shape}) are not {n_led} finite "
                            "points")
    return problems


def flat_field_problems(
    portions: np.ndarray,
    relative_intensities: np.ndarray,
    *,
    image_size: tuple[int, int] | None = None,
) -> list[str]:
    """What makes a flat field unusable; empty if it may be put in force.

    Parameters
    ----------
    portions : (K, H, W) float
        The maps: every value finite and in (0, 1].
    relative_intensities : (K,) float
        Each finite and > 0.
    image_size : (width, height), optional
        The camera's image size, when known: the maps must have it.

    Returns
    -------
    list of str
        One sentence a problem.
    """
    p = np.asarray(portions)
    e = np.asarray(relative_intensities, dtype=np.float64)
    if p.ndim != 3 or p.shape[0] < 1 or 0 in p.shape:
        return [f"flat-field maps of shape {p.shape}, expected (K, H, W), none empty"]
    problems = []
    n_led, h, w = p.shape
    if image_size is not None and tuple(image_size) != (w, h):
        problems.append(f"the maps are {w}x{h}, the camera's images "
                        f"{image_size[0]}x{image_size[1]}")
    ok = np.isfinite(p) & (p > 0) & (p <= 1)
    if not np.all(ok):
        bad = np.flatnonzero(~ok.reshape(n_led, -1).all(axis=1))
        problems.append("the maps of LED(s) " + ", ".join(map(str, bad))
                        + " have values that are not finite or not in (0, 1]")
    if e.shape != (n_led,):
        problems.append(f"{e.size} relative intensities for {n_led} maps")
    elif not np.all(np.isfinite(e) & (e > 0)):
        problems.append("relative intensities not finite and > 0: "
                        + ", ".join(f"{x:g}" for x in e))
    return problems


# ------------------------------------------------------------------------------ lights


def save_lights(directory: str | os.PathLike[str], record: LightsRecord) -> Path:
    """Write ``record`` to ``directory/lights.yaml`` (atomically); return the path.

    Raises
    ------
    FingerpsCalibError
        The directory cannot be created or written.
    """
    directory = _directory(directory)
    lights = record.lights
    tri = lights.triangulation
    leds = []
    for k in range(lights.led_count):
        entry: dict[str, Any] = {
            "index": k,
            "direction": _floats(lights.directions_optical[k]),
            "direction_ps": _floats(optical_to_ps(lights.directions_optical[k])),
            "highlight_residual_px": float(lights.residuals_px[k]),
        }
        if tri is not None:
            entry.update({
                "position_m": _floats(tri.led_positions_optical_m[k]),
                "position_residual_mm": 1e3 * float(tri.position_residuals_m[k]),
                "direction_residual_deg": float(tri.direction_residuals_deg[k]),
                "ray_angle_deg": float(tri.ray_angles_deg[k]),
                "range_uncertainty_mm": 1e3 * float(tri.range_uncertainty_m[k]),
            })
        leds.append(entry)
    placements = [{
        "sphere_center_m": _floats(pl.sphere_center_optical_m),
        "sphere_radius_m": pl.radius_m,
        "edge_rms_px": pl.edge_rms_px,
        "leds": [{
            "highlight_uv": _floats(pl.highlights_uv[k]),
            "highlight_point_m": _floats(pl.highlight_points_optical_m[k]),
            "direction": _floats(pl.directions_optical[k]),
            "highlight_residual_px": float(pl.residuals_px[k]),
        } for k in range(pl.led_count)],
    } for pl in lights.placements]
    fit: dict[str, Any] = {
        "edge_rms_px_max": float(lights.edge_rms_px),
        "highlight_residual_px_max": float(np.nanmax(lights.residuals_px)),
    }
    if tri is not None:
        fit["led_position_residual_mm_max"] = 1e3 * float(np.nanmax(tri.position_residuals_m))
        fit["direction_residual_deg_max"] = float(np.nanmax(tri.direction_residuals_deg))
    doc = {
        "format": LIGHTS_FORMAT,
        "camera_name": record.camera_name,
        "date": record.date,
        "stamp_ns": int(record.stamp_ns),
        "frame_id": record.frame_id,
        "image_width": int(record.image_width),
        "image_height": int(record.image_height),
        "camera_matrix": _floats(np.ravel(record.camera_matrix)),
        "method": ("single placement: directions from the highlight points (distant light)"
                   if tri is None else
                   f"{len(lights.placements)} placements: LED positions triangulated, "
                   "directions from the reference point"),
        "reference_point_m": None if tri is None else _floats(tri.reference_point_optical_m),
        "sphere_radius_m": float(lights.placements[-1].radius_m),
        "sphere_center_m": _floats(lights.sphere_center_optical_m),
        "fit": fit,
        "leds": leds,
        "placements": placements,
    }
    text = _LIGHTS_HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None,
                                           width=100)
    path = directory / LIGHTS_FILE
    write_atomic(path, text.encode("utf-8"))
    return path


def load_lights(directory: str | os.PathLike[str]) -> LightsRecord | None:
    """Read ``directory/lights.yaml``; None if there is none.

    Raises
    ------
    FingerpsCalibError
        The file exists but cannot be read or is not a light calibration; the message
        names the file and what to do.
    """
    path = Path(directory) / LIGHTS_FILE
    doc = _read_yaml(path, LIGHTS_FORMAT)
    if doc is None:
        return None
    try:
        placements = tuple(Placement(
            sphere_center_optical_m=pl["sphere_center_m"],
            radius_m=pl["sphere_radius_m"],
            edge_rms_px=pl["edge_rms_px"],
            highlight_points_optical_m=[led["highlight_point_m"] for led in pl["leds"]],
            directions_optical=[led["direction"] for led in pl["leds"]],
            highlights_uv=[led["highlight_uv"] for led in pl["leds"]],
            residuals_px=[led["highlight_residual_px"] for led in pl["leds"]],
        ) for pl in doc["placements"])
        leds = doc["leds"]
        directions = _array([led["direction"] for led in leds], (len(leds), 3))
        residuals = _array([led["highlight_residual_px"] for led in leds], (len(leds),))
        triangulation = None
        if doc["reference_point_m"] is not None:
            triangulation = TriangulatedLights(
                led_positions_optical_m=_array([led["position_m"] for led in leds],
                                               (len(leds), 3)),
                position_residuals_m=1e-3 * _array(
                    [led["position_residual_mm"] for led in leds], (len(leds),)),
                direction_residuals_deg=_array(
                    [led["direction_residual_deg"] for led in leds], (len(leds),)),
                ray_angles_deg=_array([led["ray_angle_deg"] for led in leds], (len(leds),)),
                range_uncertainty_m=1e-3 * _array(
                    [led["range_uncertainty_mm"] for led in leds], (len(leds),)),
                reference_point_optical_m=_array(doc["reference_point_m"], (3,)),
                directions_optical=directions,
                placements=len(placements),
                ok=True,
                problems=(),
            )
        if not placements or any(pl.led_count != len(leds) for pl in placements):
            raise ValueError("the placements do not match the LEDs")
        if not np.allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-6):
            raise ValueError("a direction is not a unit vector")
        lights = CombinedLights(
            directions_optical=directions,
            residuals_px=residuals,
            sphere_center_optical_m=_array(doc["sphere_center_m"], (3,)),
            edge_rms_px=float(doc["fit"]["edge_rms_px_max"]),
            placements=placements,
            triangulation=triangulation,
            ok=True,
            problems=(),
        )
        return LightsRecord(
            camera_name=str(doc["camera_name"]),
            frame_id=str(doc["frame_id"]),
            stamp_ns=int(doc["stamp_ns"]),
            image_width=int(doc["image_width"]),
            image_height=int(doc["image_height"]),
            camera_matrix=_array(doc["camera_matrix"], (9,)).reshape(3, 3),
            lights=lights,
        )
    except (KeyError, TypeError, ValueError, IndexError, FingerpsCalibError) as exc:
        raise FingerpsCalibError(
            f"{path} is not a complete light calibration ({type(exc).__name__}: {exc}); "
            "recalibrate the lights (the file will be replaced) or remove it"
        ) from exc


# -------------------------------------------------------------------------- flat field


def save_flat_field(directory: str | os.PathLike[str], record: FlatFieldRecord) -> Path:
    """Write ``record`` to ``directory/flat_field.yaml`` and a new maps file; return the
    YAML's path. Maps files no longer named are deleted afterwards.

    Raises
    ------
    FingerpsCalibError
        The directory cannot be created or written, or the maps are not (K, H, W).
    """
    directory = _directory(directory)
    portions = np.asarray(record.portions, dtype=np.float32)
    if portions.ndim != 3:
        raise FingerpsCalibError(f"flat-field maps have shape {portions.shape}, not (K, H, W)")
    buffer = io.BytesIO()
    np.savez_compressed(buffer, portions=portions)
    data = buffer.getvalue()
    moment = datetime.fromtimestamp(record.stamp_ns // 1_000_000_000, tz=UTC)
    maps_name = (f"flat_field_{moment.strftime('%Y%m%dT%H%M%S')}_"
                 f"{record.stamp_ns % 1_000_000_000:09d}Z.npz")
    write_atomic(directory / maps_name, data)
    n_led, height, width = portions.shape
    doc = {
        "format": FLAT_FIELD_FORMAT,
        "camera_name": record.camera_name,
        "date": record.date,
        "stamp_ns": int(record.stamp_ns),
        "frame_id": record.frame_id,
        "image_width": int(width),
        "image_height": int(height),
        "led_count": int(n_led),
        "maps_file": maps_name,
        "maps_sha256": hashlib.sha256(data).hexdigest(),
        "polynomial_degree": int(record.polynomial_degree),
        "relative_intensities": _floats(record.relative_intensities),
        "fit_residual_pct": _floats(100.0 * np.asarray(record.fit_residuals)),
    }
    text = _FLAT_HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None,
                                         width=100)
    path = directory / FLAT_FIELD_FILE
    write_atomic(path, text.encode("utf-8"))
    for stale in directory.iterdir():
        if _MAPS_PATTERN.match(stale.name) and stale.name != maps_name:
            stale.unlink(missing_ok=True)
    return path


def load_flat_field(directory: str | os.PathLike[str]) -> FlatFieldRecord | None:
    """Read ``directory/flat_field.yaml`` and its maps file; None if there is none.

    Raises
    ------
    FingerpsCalibError
        The files exist but are unreadable, incomplete or do not match (size, SHA-256).
    """
    path = Path(directory) / FLAT_FIELD_FILE
    doc = _read_yaml(path, FLAT_FIELD_FORMAT)
    if doc is None:
        return None
    redo = "recalibrate the flat field (the files will be replaced) or remove them"
    try:
        maps_path = Path(directory) / str(doc["maps_file"])
        data = maps_path.read_bytes()
        if hashlib.sha256(data).hexdigest() != doc["maps_sha256"]:
            raise FingerpsCalibError(
                f"{maps_path} does not match the SHA-256 in {path}: it was changed or "
                f"damaged; {redo}")
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            portions = np.asarray(archive["portions"], dtype=np.float32)
        expected = (int(doc["led_count"]), int(doc["image_height"]), int(doc["image_width"]))
        if portions.shape != expected:
            raise ValueError(f"maps of shape {portions.shape}, the YAML says {expected}")
        return FlatFieldRecord(
            camera_name=str(doc["camera_name"]),
            frame_id=str(doc["frame_id"]),
            stamp_ns=int(doc["stamp_ns"]),
            portions=portions,
            relative_intensities=_array(doc["relative_intensities"], (expected[0],)),
            fit_residuals=0.01 * _array(doc["fit_residual_pct"], (expected[0],)),
            polynomial_degree=int(doc["polynomial_degree"]),
        )
    except FingerpsCalibError:
        raise
    except FileNotFoundError as exc:
        raise FingerpsCalibError(f"{path} names a maps file that is missing ({exc}); {redo}") \
            from exc
    except (KeyError, TypeError, ValueError, OSError) as exc:
        raise FingerpsCalibError(
            f"{path} is not a complete flat field ({type(exc).__name__}: {exc}); {redo}"
        ) from exc


# ----------------------------------------------------------------------------- files


def write_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same directory, flushed to
    disk and renamed over ``path``; on failure ``path`` is untouched.

    Raises
    ------
    FingerpsCalibError
        The file cannot be written (the message names it).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise FingerpsCalibError(
            f"cannot write {path}: {exc}; check that the directory is writable and the disk "
            "not full (the previous calibration is unchanged)") from exc


def _directory(directory: str | os.PathLike[str]) -> Path:
    path = Path(directory).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FingerpsCalibError(
            f"cannot create the calibration directory {path}: {exc}; set calibration_dir "
            "to a writable directory") from exc
    return path


def _read_yaml(path: Path, expected_format: str) -> dict[str, Any] | None:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise FingerpsCalibError(f"cannot read {path}: {exc}") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        reason = " ".join(str(exc).split())  # one line
        raise FingerpsCalibError(
            f"{path} is not valid YAML ({reason}); recalibrate (the file will be replaced) "
            "or remove it") from exc
    if not isinstance(doc, dict) or doc.get("format") != expected_format:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise FingerpsCalibError(
            f"{path} is not a {expected_format} file (format: {found!r}); recalibrate or "
            "remove it")
    return doc


def _floats(values: np.ndarray) -> list[float]:
    return [float(x) for x in np.ravel(values)]


def _array(values: Any, shape: tuple[int, ...]) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"expected shape {shape}, got {array.shape}")
    return array
