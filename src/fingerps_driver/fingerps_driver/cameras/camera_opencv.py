"""A real camera through OpenCV's ``cv2.VideoCapture`` (V4L2 on Linux): USB/UVC and MIPI
cameras with a V4L2 driver.

Settings go through ``VideoCapture.set`` properties, in the order V4L2 needs them: pixel
format (FOURCC) and RGB conversion, then resolution, frame rate, buffer count, manual
exposure, gain, read timeout. A backend may refuse a property (``set`` returns False); the
camera then goes on and lists the refusal in ``refused_settings`` for the caller to report.
The resolution is checked on the first frame at ``open`` and on every frame after.

Units: exposure in seconds. V4L2's ``exposure_time_absolute`` control (what
``CAP_PROP_EXPOSURE`` maps to under ``CAP_V4L2``) counts 100 µs steps, so under V4L2 the
camera sends ``exposure_s / 100e-6`` after switching auto exposure off
(``CAP_PROP_AUTO_EXPOSURE`` = 1, V4L2_EXPOSURE_MANUAL); other APIs get seconds. Gain is in
the device's own units.

Stale frames: a free-running camera queues frames, and the frame being exposed when an LED
switched mixes two lights. The camera asks for one driver buffer and drops
``discard_frames`` frames before the one it returns (default 1), so a frame is exposed
entirely after the grab was asked for.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from fingerps_driver.cameras.camera import (
    Camera,
    check_encoding,
    check_frame,
    check_requested_size,
    to_mono,
)
from fingerps_driver.errors import CameraError

V4L2_EXPOSURE_UNIT_S = 100e-6
"""One step of V4L2's exposure_time_absolute control."""
V4L2_EXPOSURE_MANUAL = 1
"""V4L2_CID_EXPOSURE_AUTO value for manual exposure (``CAP_PROP_AUTO_EXPOSURE``)."""
MONO16_FOURCC = "Y16 "
"""V4L2 16-bit greyscale pixel format, used by default for mono16."""


def parse_device(device: str) -> str | int:
    """A device parameter as VideoCapture takes it: ``"2"`` -> 2, ``"/dev/video0"`` as is."""
    text = device.strip()
    return int(text) if text.isdigit() else text


class OpenCvCamera(Camera):
    """Monochrome frames from ``cv2.VideoCapture``.

    Parameters
    ----------
    device : str or int
        Device path (``"/dev/video0"``, or ``/dev/v4l/by-id/...`` for a stable name), camera
        index, or — with ``api=cv2.CAP_ANY``/``CAP_IMAGES`` — a video file or an image
        sequence pattern (``"frame_%03d.png"``).
    width, height : int
        Resolution to ask for; 0 keeps the camera's. Whatever is asked, the frames must
        all have the size of the first one.
    fps : float
        Frame rate to ask for; 0 keeps the camera's.
    exposure_s : float
        Manual exposure time in seconds; 0 leaves the camera's (auto) exposure alone.
    gain : float
        Gain in device units; negative leaves it alone.
    pixel_format : str
        ``"mono8"`` (colour is converted to grey) or ``"mono16"`` (the camera must deliver
        16-bit frames; under V4L2 this asks for FOURCC ``Y16 `` without RGB conversion).
    fourcc : str
        Four-character V4L2 pixel format to ask for (``"GREY"``, ``"YUYV"``, ``"MJPG"``);
        empty: the default of ``pixel_format`` (none for mono8, ``Y16 `` for mono16).
    discard_frames : int
        Frames dropped before each one returned by ``grab`` (see the module docstring).
    api : int
        OpenCV backend, ``cv2.CAP_V4L2`` by default.
    capture_factory : callable
        ``capture_factory(device, api)`` -> a ``cv2.VideoCapture``-like object (tests).
    """

    def __init__(
        self,
        device: str | int,
        *,
        width: int = 0,
        height: int = 0,
        fps: float = 0.0,
        exposure_s: float = 0.0,
        gain: float = -1.0,
        pixel_format: str = "mono8",
        fourcc: str = "",
        discard_frames: int = 1,
        api: int = cv2.CAP_V4L2,
        capture_factory: Callable[[Any, int], Any] = cv2.VideoCapture,
    ) -> None:
        check_encoding(pixel_format, name="pixel_format")
        check_requested_size(width, height, name="resolution")
        if not (math.isfinite(fps) and fps >= 0):
            raise ValueError(f"fps {fps} must be >= 0")
        if not (math.isfinite(exposure_s) and exposure_s >= 0):
            raise ValueError(f"exposure_s {exposure_s} must be >= 0")
        if fourcc and len(fourcc) != 4:
            raise ValueError(f"fourcc {fourcc!r} must be four characters")
        if discard_frames < 0:
            raise ValueError(f"discard_frames {discard_frames} must be >= 0")
        super().__init__(f"camera {device!r}", width=width, height=height, encoding=pixel_format)
        self._device = device
        self._size = (width, height)
        self._fps = fps
        self._exposure_s = exposure_s
        self._gain = gain
        self._fourcc = fourcc or (MONO16_FOURCC if pixel_format == "mono16" else "")
        self._discard = discard_frames
        self._api = api
        self._factory = capture_factory
        self._capture: Any = None
        self._timeout_ms = 0.0

    @property
    def is_open(self) -> bool:
        return self._capture is not None

    def _acquire(self) -> None:
        """Open the device, apply the settings and read a first frame to learn its size.

        Raises
        ------
        CameraError
            The device cannot be opened, delivers no frame, or a frame of another size
            or bit depth than asked for. The message names the device.
        """
        capture = self._factory(self._device, self._api)
        if not capture.isOpened():
            capture.release()
            raise CameraError(
                f"cannot open {self.source}: check that it exists (`v4l2-ctl "
                "--list-devices`), that no other program uses it, and that the user is in "
                "the 'video' group")
        self._capture = capture
        self.refused_settings = []
        try:
            self._configure()
            ok, frame = capture.read()
            image = to_mono(frame if ok else None, encoding=self._encoding, source=self.source)
            height, width = image.shape
            if self._size != (0, 0) and (width, height) != self._size:
                raise CameraError(
                    f"{self.source} delivers {width}x{height} frames, not the "
                    f"{self._size[0]}x{self._size[1]} asked for; pick a resolution it "
                    "offers (`v4l2-ctl --list-formats-ext`)")
            self._width, self._height = width, height
        except CameraError:
            self.close()
            raise

    def _release(self) -> None:
        capture, self._capture = self._capture, None
        if capture is not None:
            capture.release()

    def set_exposure(self, exposure_s: float) -> None:
        """Manual exposure of ``exposure_s`` seconds from the next frame on (if it changed).

        A refusal by the backend is recorded in ``refused_settings``, not raised: the
        camera keeps working with its own exposure.
        """
        if not (math.isfinite(exposure_s) and exposure_s > 0):
            raise ValueError(f"exposure_s {exposure_s} must be > 0")
        if exposure_s == self._exposure_s or self._capture is None:
            self._exposure_s = exposure_s
            return
        self._exposure_s = exposure_s
        self._set_exposure()

    def _frame(self, timeout_s: float) -> np.ndarray:
        """One frame exposed after this call began."""
        capture = self._capture
        timeout_ms = round(timeout_s * 1e3)
        if self._api == cv2.CAP_V4L2 and timeout_ms != self._timeout_ms:
            self._timeout_ms = timeout_ms
            self._set("read_timeout_ms", cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms)
        for _ in range(self._discard):
            if not capture.grab():
                raise CameraError(f"no frame from {self.source} within {timeout_s:.3f} s")
        ok, frame = capture.read()
        if not ok or frame is None:
            raise CameraError(f"no frame from {self.source} within {timeout_s:.3f} s")
        image = to_mono(frame, encoding=self._encoding, source=self.source)
        return check_frame(image, width=self._width, height=self._height, source=self.source)

    # -- settings ----------------------------------------------------------------------

    def _configure(self) -> None:
        if self._fourcc:
            self._set("fourcc", cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self._fourcc),
                      shown=self._fourcc)
        if self._encoding == "mono16" or self._fourcc == "GREY":
            self._set("convert_rgb", cv2.CAP_PROP_CONVERT_RGB, 0)  # keep the raw grey data
        if self._size != (0, 0):
            self._set("width", cv2.CAP_PROP_FRAME_WIDTH, self._size[0])
            self._set("height", cv2.CAP_PROP_FRAME_HEIGHT, self._size[1])
        if self._fps > 0:
            self._set("fps", cv2.CAP_PROP_FPS, self._fps)
        if self._api == cv2.CAP_V4L2:
            self._set("buffers", cv2.CAP_PROP_BUFFERSIZE, 1)
        if self._exposure_s > 0:
            self._set_exposure()
        if self._gain >= 0:
            self._set("gain", cv2.CAP_PROP_GAIN, self._gain)

    def _set_exposure(self) -> None:
        if self._api == cv2.CAP_V4L2:
            self._set("auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL,
                      shown="manual")
            value = self._exposure_s / V4L2_EXPOSURE_UNIT_S
        else:
            value = self._exposure_s
        self._set("exposure", cv2.CAP_PROP_EXPOSURE, value, shown=f"{self._exposure_s:g} s")

    def _set(self, name: str, prop: int, value: float, *, shown: str = "") -> None:
        assert self._capture is not None
        if not self._capture.set(prop, float(value)):
            refusal = f"{name}={shown or f'{value:g}'}"
            if refusal not in self.refused_settings:  # per-LED exposures repeat every burst
                self.refused_settings.append(refusal)
