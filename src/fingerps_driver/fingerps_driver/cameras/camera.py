"""Camera base class of the driver, the frame checks every backend shares, and a simulated
camera.

``Camera`` is the one base class of every backend and the interface the burst sequencer
needs: it owns the lifecycle (open, close, ``with``) and the checks of ``grab``; a backend
implements only how it acquires, releases and reads its device. A camera whose exposure can
be set between frames also provides ``ExposureControl``. Backends:

- ``SimulatedCamera`` (here) renders whatever LEDs the board has *actually* lit when
  ``grab`` is called (it asks a ``lit_leds`` callable, normally reading
  ``BoardEmulator.lit_leds``), so a simulated burst goes through the serial path exactly
  like a real one;
- ``camera_opencv.OpenCvCamera``: a real camera through OpenCV (V4L2 on Linux);
- ``camera_folder.FolderCamera``: replays a folder of images taken elsewhere.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from fingerps_driver.device import Device
from fingerps_driver.errors import CameraError, FingerpsDriverError

ENCODING_DTYPES = {"mono8": np.dtype(np.uint8), "mono16": np.dtype(np.uint16)}
"""Supported image encodings (sensor_msgs/Image names) and their dtypes."""


@runtime_checkable
class ExposureControl(Protocol):
    """A camera whose exposure time can be changed between frames."""

    def set_exposure(self, exposure_s: float) -> None:
        """Use ``exposure_s`` seconds from the next frame on.

        Raises ``CameraError`` if the camera fails; a backend may instead record a setting
        the device refuses and go on (``refused_settings``).
        """
        ...


def check_encoding(encoding: str, *, name: str = "encoding") -> None:
    """Raise ``ValueError`` (a programming error) unless ``encoding`` is a supported one."""
    if encoding not in ENCODING_DTYPES:
        raise ValueError(f"{name} {encoding!r} is not one of {sorted(ENCODING_DTYPES)}")


def check_requested_size(width: int, height: int, *, name: str) -> None:
    """Raise ``ValueError`` unless a size asked for is both (> 0) or neither (0, the device's)."""
    if width < 0 or height < 0 or (width == 0) != (height == 0):
        raise ValueError(f"{name} {width}x{height}: give both (> 0) or neither (0)")


def to_mono(frame: object, *, encoding: str, source: str) -> np.ndarray:
    """One camera frame as a monochrome image of ``encoding``.

    Parameters
    ----------
    frame : (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA array, or None
        What the backend delivered (OpenCV channel order). Colour is converted with
        ``cv2.cvtColor`` (Rec. 601 luma, 0.299 R + 0.587 G + 0.114 B).
    encoding : str
        ``"mono8"`` (needs uint8 data) or ``"mono16"`` (needs uint16 data). Bit depth is
        never invented or thrown away: an 8-bit frame for mono16 (or the reverse) is an
        error.
    source : str
        Names the camera in error messages.

    Returns
    -------
    image : (H, W) uint8 or uint16
        A new C-contiguous array.

    Raises
    ------
    CameraError
        No frame, or a frame that cannot be made into ``encoding``.
    """
    check_encoding(encoding)
    if frame is None:
        raise CameraError(f"no frame from {source}")
    if not isinstance(frame, np.ndarray):
        raise CameraError(f"{source} delivered a {type(frame).__name__}, not an image")
    dtype = ENCODING_DTYPES[encoding]
    if frame.dtype != dtype:
        hint = {"mono8": "mono16", "mono16": "mono8"}[encoding]
        raise CameraError(
            f"{source} delivered {frame.dtype} pixels, not {dtype} for {encoding}; set the "
            f"pixel format to {hint} (or make the camera deliver {encoding})")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim == 3 and frame.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if frame.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(np.ascontiguousarray(frame), code)
    if frame.ndim != 2 or frame.size == 0:
        raise CameraError(f"{source} delivered a frame of shape {frame.shape}, not an image")
    return np.array(frame, dtype=dtype, order="C", copy=True)


def check_frame(image: np.ndarray, *, width: int, height: int, source: str) -> np.ndarray:
    """Return ``image`` if it is (height, width); else raise ``CameraError`` saying so."""
    if image.shape != (height, width):
        raise CameraError(
            f"{source} delivered a frame of {image.shape[1]}x{image.shape[0]} instead of "
            f"{width}x{height}; check the camera's resolution")
    return image


class Camera(Device):
    """A monochrome camera delivering one frame per ``grab``: what every backend shares.

    The base owns the lifecycle (``open``/``close``/``with`` of ``fingerps_driver.device.Device``),
    the size and encoding, the checks of ``grab`` (a positive timeout, an open camera) and
    the frame counter. A backend implements only what differs: ``is_open``, ``_acquire``,
    ``_release`` and ``_frame``.

    Parameters
    ----------
    source : str
        The camera as named in messages (``"camera '/dev/video0'"``).
    width, height : int
        Frame size in pixels; a backend that learns it at ``open`` sets it then.
    encoding : str
        ``"mono8"`` or ``"mono16"``; likewise.
    """

    def __init__(self, source: str, *, width: int, height: int, encoding: str) -> None:
        self._source = source
        self._width = width
        self._height = height
        self._encoding = encoding
        self.frames_grabbed = 0
        """Frames returned by ``grab`` since construction."""
        self.refused_settings: list[str] = []
        """Settings the device refused (``"fps=60"``...) since the last ``open``, kept for
        the caller to report; only a backend that goes on after a refusal (``OpenCvCamera``)
        adds to it."""

    @property
    def width(self) -> int:
        """Image width in pixels (columns)."""
        return self._width

    @property
    def height(self) -> int:
        """Image height in pixels (rows)."""
        return self._height

    @property
    def encoding(self) -> str:
        """``"mono8"`` (uint8 frames) or ``"mono16"`` (uint16 frames)."""
        return self._encoding

    def grab(self, *, timeout_s: float) -> np.ndarray:
        """Capture one frame now.

        Returns
        -------
        image : (height, width) uint8 or uint16
            A new array the caller owns.

        Raises
        ------
        CameraError
            If the camera is not open, or no valid frame arrives within ``timeout_s``.
        ValueError
            If ``timeout_s`` is not > 0.
        """
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        if not self.is_open:
            raise CameraError(f"{self.source} is not open; call open() first")
        image = self._frame(timeout_s)
        self.frames_grabbed += 1
        return image

    @property
    def source(self) -> str:
        """The camera as named in messages."""
        return self._source

    @abstractmethod
    def _frame(self, timeout_s: float) -> np.ndarray:
        """One checked frame of the open camera (``grab`` without its checks)."""


class SimulatedCamera(Camera):
    """Camera whose frames are rendered from the LEDs lit at grab time.

    Parameters
    ----------
    render : callable
        ``render(lit) -> image``: ``lit`` is the ascending tuple of lit LED indices,
        ``image`` a new (height, width) array of the encoding's dtype (grab hands it
        on without copying).
    lit_leds : callable
        Returns the indices of the LEDs physically lit now (e.g.
        ``BoardEmulator.lit_leds``).
    width, height : int
        Frame size in pixels.
    encoding : str
        ``"mono8"`` or ``"mono16"``.
    """

    def __init__(
        self,
        render: Callable[[Sequence[int]], np.ndarray],
        lit_leds: Callable[[], Sequence[int]],
        *,
        width: int,
        height: int,
        encoding: str = "mono8",
    ) -> None:
        check_encoding(encoding)
        if width < 1 or height < 1:
            raise ValueError(f"frame size {width}x{height} must be positive")
        super().__init__("SimulatedCamera", width=width, height=height, encoding=encoding)
        self._render = render
        self._lit_leds = lit_leds
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def _acquire(self) -> None:
        self._open = True

    def _release(self) -> None:
        self._open = False

    def _frame(self, timeout_s: float) -> np.ndarray:
        """Render one frame of the LEDs lit now.

        A failure of ``render`` is reported as ``CameraError`` (as a real camera's failure
        to deliver a frame would be), with the original exception chained.
        """
        try:
            lit = tuple(sorted(self._lit_leds()))
        except FingerpsDriverError as exc:
            raise CameraError(f"no frame: cannot see which LEDs are lit ({exc})") from exc
        try:
            image = self._render(lit)
        except Exception as exc:  # the simulated sensor failed: no frame
            raise CameraError(f"no frame: rendering LEDs {lit} failed ({exc!r})") from exc
        if not isinstance(image, np.ndarray):
            raise CameraError(f"no frame: render returned {type(image).__name__}, not an array")
        expected = (self._height, self._width)
        if image.shape != expected:
            raise CameraError(
                f"frame of shape {image.shape} instead of {expected}; the renderer and the "
                f"camera's width/height disagree"
            )
        if image.dtype != ENCODING_DTYPES[self._encoding]:
            raise CameraError(
                f"frame of dtype {image.dtype} for encoding {self._encoding} "
                f"(needs {ENCODING_DTYPES[self._encoding]})"
            )
        return image
