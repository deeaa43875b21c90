"""Read and write the ROS camera_info YAML file.

The format is the one ``camera_calibration`` writes and ``camera_info_manager`` reads
(``camera_calibration_parsers``)::

    image_width: 659
    image_height: 493
    camera_name: fingerps_camera
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}
    projection_matrix: {rows: 3, cols: 4, data: [...]}

``image_width``, ``image_height``, ``camera_matrix``, ``distortion_model`` and
``distortion_coefficients`` are required. As in ``camera_calibration_parsers``, a missing
``camera_name`` reads as ``"unknown"``; a missing ``rectification_matrix`` reads as the
identity and a missing ``projection_matrix`` as ``[K | 0]`` (a monocular camera).
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from fingerps_calib.errors import FingerpsCalibError

#: Number of coefficients each distortion model needs (other models: any number).
DISTORTION_LENGTHS: dict[str, tuple[int, ...]] = {
    "plumb_bob": (5,),
    "rational_polynomial": (8,),
    "equidistant": (4,),
}

_RECALIBRATE = "recalibrate with `ros2 run camera_calibration cameracalibrator` or fix the file"


@dataclass(frozen=True, eq=False)
class CameraIntrinsics:
    """Intrinsics of one camera, as in sensor_msgs/CameraInfo.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    camera_matrix : (3, 3) float64
        K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels.
    distortion_model : str
        ``"plumb_bob"``, ``"rational_polynomial"``, ``"equidistant"``, ...
    distortion : (n,) float64
        Distortion coefficients (OpenCV order for plumb_bob: k1, k2, p1, p2, k3).
    camera_name : str
    rectification : (3, 3) float64
        R; the identity for a monocular camera.
    projection : (3, 4) float64
        P; ``[K | 0]`` for a monocular camera.

    Arrays are stored as read-only float64 copies. Bad shapes or values raise
    `FingerpsCalibError`.
    """

    width: int
    height: int
    camera_matrix: np.ndarray
    distortion_model: str
    distortion: np.ndarray
    camera_name: str = "unknown"
    rectification: np.ndarray | None = field(default=None)
    projection: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height:
            raise FingerpsCalibError(
                f"image size {self.width}x{self.height} is not integral; {_RECALIBRATE}"
            )
        if self.width <= 0 or self.height <= 0:
            raise FingerpsCalibError(
                f"image size {self.width}x{self.height} must be positive; {_RECALIBRATE}"
            )
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        k = _frozen_array(self.camera_matrix, (3, 3), "camera_matrix")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0.0, 0.0, 1.0]):
            raise FingerpsCalibError(
                f"camera_matrix {k.ravel().tolist()} is not [[fx,0,cx],[0,fy,cy],[0,0,1]] "
                f"with fx, fy > 0; {_RECALIBRATE}"
            )
        object.__setattr__(self, "camera_matrix", k)
        d = _frozen_array(np.ravel(np.asarray(self.distortion, dtype=float)), None,
                          "distortion")
        wanted = DISTORTION_LENGTHS.get(self.distortion_model)
        if wanted is not None and d.size not in wanted:
            raise FingerpsCalibError(
                f"distortion model {self.distortion_model!r} needs {wanted[0]} coefficients, "
                f"got {d.size}; {_RECALIBRATE}"
            )
        object.__setattr__(self, "distortion", d)
        r = np.eye(3) if self.rectification is None else self.rectification
        object.__setattr__(self, "rectification", _frozen_array(r, (3, 3), "rectification"))
        p = np.hstack([k, np.zeros((3, 1))]) if self.projection is None else self.projection
        object.__setattr__(self, "projection", _frozen_array(p, (3, 4), "projection"))
        object.__setattr__(self, "camera_name", str(self.camera_name))
        object.__setattr__(self, "distortion_model", str(self.distortion_model))

    @property
    def fx(self) -> float:
        """Focal length along u, pixels."""
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along v, pixels."""
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        """Principal point u, pixels."""
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        """Principal point v, pixels."""
        return float(self.camera_matrix[1, 2])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraIntrinsics):
            return NotImplemented
        return (
            (self.width, self.height, self.camera_name, self.distortion_model)
            == (other.width, other.height, other.camera_name, other.distortion_model)
            and self.distortion.shape == other.distortion.shape
            and all(
                np.array_equal(a, b)
                for a, b in (
                    (self.camera_matrix, other.camera_matrix),
                    (self.distortion, other.distortion),
                    (self.rectification, other.rectification),
                    (self.projection, other.projection),
                )
            )
        )

    __hash__ = None  # type: ignore[assignment]


def load_camera_info(path: str | os.PathLike[str]) -> CameraIntrinsics:
    """Read a camera_info YAML file.

    Parameters
    ----------
    path : str or path-like
        File written by ``camera_calibration`` / ``camera_info_manager``.

    Returns
    -------
    CameraIntrinsics

    Raises
    ------
    FingerpsCalibError
        The file is missing or unreadable, a required key is missing, or a matrix has
        the wrong shape; the message names the file and the key.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FingerpsCalibError(
            f"camera info file {path} does not exist; calibrate the camera "
            "(`ros2 run fingerps_calib calibrate_camera` on checkerboard images, or "
            "`ros2 run camera_calibration cameracalibrator`) and save the result there, "
            "or pass the right path"
        ) from None
    except OSError as exc:
        raise FingerpsCalibError(f"cannot read camera info file {path}: {exc}") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FingerpsCalibError(
            f"camera info file {path} is not valid YAML ({exc}); {_RECALIBRATE}"
        ) from exc
    if not isinstance(doc, dict):
        raise FingerpsCalibError(
            f"camera info file {path} does not hold a YAML mapping; {_RECALIBRATE}"
        )

    def required(key: str) -> object:
        if key not in doc or doc[key] is None:
            raise FingerpsCalibError(
                f"camera info file {path} has no key {key!r}; {_RECALIBRATE}"
            )
        return doc[key]

    def matrix(key: str, shape: tuple[int, int] | None) -> np.ndarray:
        node = required(key)
        if not isinstance(node, dict) or not {"rows", "cols", "data"} <= node.keys():
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} must be a mapping with rows, cols "
                f"and data; {_RECALIBRATE}"
            )
        try:
            rows, cols = int(node["rows"]), int(node["cols"])
            data = np.asarray(node["data"], dtype=float).ravel()
        except (TypeError, ValueError) as exc:
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} has non-numeric entries ({exc}); "
                f"{_RECALIBRATE}"
            ) from exc
        if data.size != rows * cols:
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} says {rows}x{cols} but holds "
                f"{data.size} numbers; {_RECALIBRATE}"
            )
        if shape is not None and (rows, cols) != shape:
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} is {rows}x{cols}, expected "
                f"{shape[0]}x{shape[1]}; {_RECALIBRATE}"
            )
        if not np.all(np.isfinite(data)):
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} holds non-finite numbers; "
                f"{_RECALIBRATE}"
            )
        return data.reshape(rows, cols)

    def integer(key: str) -> int:
        value = required(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise FingerpsCalibError(
                f"camera info file {path}: key {key!r} must be an integer, got {value!r}; "
                f"{_RECALIBRATE}"
            )
        return value

    width, height = integer("image_width"), integer("image_height")
    camera_matrix = matrix("camera_matrix", (3, 3))
    model = required("distortion_model")
    distortion = matrix("distortion_coefficients", None).ravel()
    rectification = matrix("rectification_matrix", (3, 3)) if "rectification_matrix" in doc \
        else None
    projection = matrix("projection_matrix", (3, 4)) if "projection_matrix" in doc else None
    try:
        return CameraIntrinsics(
            width=width,
            height=height,
            camera_matrix=camera_matrix,
            distortion_model=str(model),
            distortion=distortion,
            camera_name=str(doc.get("camera_name") or "unknown"),
            rectification=rectification,
            projection=projection,
        )
    except FingerpsCalibError as exc:
        raise FingerpsCalibError(f"camera info file {path}: {exc}") from exc


def save_camera_info(path: str | os.PathLike[str], intrinsics: CameraIntrinsics) -> None:
    """Write ``intrinsics`` as a camera_info YAML file (the layout camera_calibration writes).

    The file is written owner-only (0600) to a temporary name next to ``path``, flushed to
    disk and then renamed, so a crash never leaves a half-written calibration. Numbers are
    written with full precision (``repr``), so `load_camera_info` reads back the same values.

    Parameters
    ----------
    path : str or path-like
    intrinsics : CameraIntrinsics

    Raises
    ------
    FingerpsCalibError
        The file cannot be written.
    """
    path = Path(path)

    def block(name: str, array: np.ndarray) -> str:
        rows, cols = (1, array.size) if array.ndim == 1 else array.shape
        data = ", ".join(_number(x) for x in np.ravel(array))
        return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]\n"

    text = (
        f"image_width: {intrinsics.width}\n"
        f"image_height: {intrinsics.height}\n"
        f"camera_name: {_scalar(intrinsics.camera_name)}\n"
        + block("camera_matrix", intrinsics.camera_matrix)
        + f"distortion_model: {_scalar(intrinsics.distortion_model)}\n"
        + block("distortion_coefficients", intrinsics.distortion)
        + block("rectification_matrix", intrinsics.rectification)
        + block("projection_matrix", intrinsics.projection)
    )
    tmp: Path | None = None
    try:
        # mkstemp: a name of this writer's own, created owner-only (0600) whatever the umask
        handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        tmp = Path(name)
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
        _sync_folder(path.parent)
    except OSError as exc:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise FingerpsCalibError(
            f"cannot write camera info file {path}: {exc}; check that the directory exists "
            "and is writable"
        ) from exc


def _sync_folder(folder: Path) -> None:
    """Flush a rename in ``folder`` to disk (best effort: not every file system can)."""
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(handle)
    except OSError:
        pass
    finally:
        os.close(handle)


def _frozen_array(value: object, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FingerpsCalibError(f"{name} is not numeric ({exc}); {_RECALIBRATE}") from exc
    if shape is not None and array.shape != shape:
        raise FingerpsCalibError(
            f"{name} has shape {array.shape}, expected {shape}; {_RECALIBRATE}"
        )
    if not np.all(np.isfinite(array)):
        raise FingerpsCalibError(f"{name} holds non-finite numbers; {_RECALIBRATE}")
    array.setflags(write=False)
    return array


def _number(x: float) -> str:
    return repr(float(x))  # shortest text that reads back to the same double


def _scalar(text: str) -> str:
    # Let PyYAML quote the string only when it must (e.g. "yes", "1", ": ").
    return yaml.safe_dump(text, default_flow_style=True).removesuffix("\n...\n").strip()
