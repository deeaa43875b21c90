"""Burst sequencing: one frame per LED, each lit alone and acknowledged before the grab.

No ROS here: the driver node calls ``capture_burst`` and converts the ``BurstResult``.
A burst is all or nothing: any failure gives ``ok=False`` with a reason and no frames.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from fingerps_driver.board.board_protocol import MAX_LEVEL
from fingerps_driver.cameras.camera import ENCODING_DTYPES, Camera, ExposureControl
from fingerps_driver.errors import FingerpsDriverError

DARK_LED = 255
"""``CapturedFrame.led_index`` of a dark (all LEDs off) frame."""


class LedSwitch(Protocol):
    """What ``capture_burst`` needs of the LED board (``LedBoard`` provides it)."""

    def set_leds(self, mask: int) -> int:
        """Light exactly ``mask``; return the mask the board acknowledged."""
        ...

    def all_off(self) -> None:
        """Switch every LED off, acknowledged."""
        ...

    def set_level(self, index: int, level: int) -> None:
        """Drive level 0..255 of LED ``index``."""
        ...


@dataclass(frozen=True)
class CapturedFrame:
    """One frame of a burst.

    Attributes
    ----------
    led_index : int
        The LED lit (alone) during the frame, 0-based; ``DARK_LED`` (255) for a dark frame.
    image : (H, W) uint8 or uint16
        The frame as the camera delivered it.
    stamp_ns : int
        ``clock()`` when the board had acknowledged the switch, just before the grab.
    exposure_s : float
        Exposure time in seconds.
    level : float
        Relative drive level of the lit LED, 0..1, as programmed on the board
        (quantised to 1/255); 0 for a dark frame.
    """

    led_index: int
    image: np.ndarray
    stamp_ns: int
    exposure_s: float
    level: float


class BurstStep(Enum):
    """The step of a burst that failed (``BurstResult.failed_step``)."""

    BOARD = "board"        # refused: the board is away (driver_core)
    LEVEL = "level"        # an LED's level set on the board
    EXPOSURE = "exposure"  # the camera's exposure set
    SWITCH = "switch"      # an LED switched on alone
    GRAB = "grab"          # an LED's frame grabbed
    REPEAT = "repeat"      # the first LED's frame grabbed again
    OFF = "off"            # the LEDs switched off
    DARK = "dark"          # the dark frame grabbed

    @property
    def at_camera(self) -> bool:
        """Whether the step is the camera's (a grab or an exposure change)."""
        return self in (BurstStep.GRAB, BurstStep.DARK, BurstStep.EXPOSURE, BurstStep.REPEAT)


@dataclass(frozen=True)
class BurstResult:
    """Outcome of ``capture_burst``.

    Attributes
    ----------
    burst_id : int
        As passed in.
    frames : tuple of CapturedFrame
        One frame per entry of ``led_order``, in that order; empty unless ``ok``.
    dark : CapturedFrame or None
        The dark frame if asked for and ``ok``.
    ok : bool
        True only for a complete burst.
    reason : str
        Why the burst failed (step, LED, error and what to do); ``""`` when ok.
    duration_s : float
        Wall time from the first command to the last, failure or not.
    failed_step : BurstStep or None
        The step that failed; None when ok.
    error_type : type or None
        The class of the error that failed it (``BoardDisconnectedError``, ``CameraError``,
        ...); None when ok or when the step failed a check (a frame of the wrong size...).
    repeat : CapturedFrame or None
        The first LED of ``led_order`` lit again after the last one, if asked for and ok.
    """

    burst_id: int
    frames: tuple[CapturedFrame, ...]
    dark: CapturedFrame | None
    ok: bool
    reason: str
    duration_s: float
    failed_step: BurstStep | None = None
    error_type: type[Exception] | None = None
    repeat: CapturedFrame | None = None

    @property
    def camera_failed(self) -> bool:
        """True if the burst failed at the camera (a grab or an exposure change)."""
        return self.failed_step is not None and self.failed_step.at_camera


class _StepFailedError(Exception):
    """A step of the burst failed; the message names the step and the LED."""

    def __init__(self, step: BurstStep, led: int | None, detail: str | Exception) -> None:
        where = f"step '{step.value}'" + ("" if led is None else f" LED {led}")
        self.step = step
        self.error_type = type(detail) if isinstance(detail, Exception) else None
        if isinstance(detail, Exception):
            detail = f"{type(detail).__name__}: {detail}"
        super().__init__(f"{where}: {detail}")


@contextmanager
def _step(step: BurstStep, led: int | None) -> Iterator[None]:
    """Report a driver error raised within as ``_StepFailedError`` naming ``step`` and ``led``."""
    try:
        yield
    except FingerpsDriverError as exc:
        raise _StepFailedError(step, led, exc) from exc


def _per_led(name: str, value: float | Sequence[float], count: int) -> tuple[float, ...]:
    values = (value,) * count if isinstance(value, (int, float)) else tuple(value)
    if len(values) != count:
        raise ValueError(f"{name} has {len(values)} entries for {count} LEDs in led_order")
    return tuple(float(v) for v in values)


def capture_burst(
    board: LedSwitch,
    camera: Camera,
    *,
    burst_id: int,
    led_order: Sequence[int],
    exposures_s: float | Sequence[float],
    levels: float | Sequence[float],
    with_dark: bool = False,
    repeat_first: bool = False,
    expected_shape: tuple[int, int] | None = None,
    grab_timeout_s: float = 0.1,
    clock: Callable[[], int] = time.time_ns,
) -> BurstResult:
    """Capture one burst: for each LED, light it alone, wait for the ack, grab, tag.

    Parameters
    ----------
    board : LedSwitch
        The open LED board (``LedBoard``).
    camera : Camera
        The open camera. If it provides ``ExposureControl``, its exposure is set to each
        LED's before that LED is switched on; otherwise it is assumed configured for
        ``exposures_s`` (which are then only recorded in the tags).
    burst_id : int
        Copied into the result.
    led_order : sequence of int
        LEDs to capture, in order (0-based, < 255).
    exposures_s : float or sequence of float
        Exposure per LED (or one for all), seconds > 0; recorded in the tags and added
        to ``grab_timeout_s`` for each grab.
    levels : float or sequence of float
        Relative drive level per LED (or one for all), 0..1; programmed on the board
        (``round(255 * level)``) before the first switch.
    with_dark : bool
        Also grab a dark frame after all LEDs are off, with the longest exposure.
    repeat_first : bool
        After the last LED, light the first LED of ``led_order`` again and grab it
        (``BurstResult.repeat``): a still finger gives the same frame twice.
    expected_shape : (H, W) or None
        Frame shape every grab must have; default ``(camera.height, camera.width)``.
    grab_timeout_s : float
        Grab timeout on top of the exposure.
    clock : callable
        Integer-nanosecond clock for ``stamp_ns`` (default ``time.time_ns``).

    Returns
    -------
    BurstResult
        ``ok=True`` with every frame, or ``ok=False`` with a reason and no frames. All LEDs
        are switched off at the end in both cases (best effort after a failure).

    Raises
    ------
    ValueError
        Only for invalid arguments (a programming error); board and camera failures are
        reported in the result.
    """
    order = tuple(int(led) for led in led_order)
    if not order:
        raise ValueError("led_order is empty")
    if any(not 0 <= led < DARK_LED for led in order):
        raise ValueError(f"led_order {order} holds an index outside 0..{DARK_LED - 1}")
    exposures = _per_led("exposures_s", exposures_s, len(order))
    if any(not (math.isfinite(e) and e > 0) for e in exposures):
        raise ValueError(f"exposures_s {exposures} must be finite and > 0")
    codes = tuple(round(MAX_LEVEL * v) for v in _per_led("levels", levels, len(order)))
    if any(not 0 <= c <= MAX_LEVEL for c in codes):
        raise ValueError(f"levels {levels} must lie in 0..1")
    programmed: dict[int, int] = {}
    for led, code in zip(order, codes, strict=True):
        if programmed.setdefault(led, code) != code:
            raise ValueError(f"LED {led} appears twice in led_order with different levels")
    if grab_timeout_s <= 0:
        raise ValueError(f"grab_timeout_s must be > 0, got {grab_timeout_s}")
    shape = tuple(expected_shape) if expected_shape is not None else (
        camera.height, camera.width)
    dtype = ENCODING_DTYPES.get(camera.encoding)

    exposure_control = camera if isinstance(camera, ExposureControl) else None

    def expose(exposure: float, led: int | None) -> None:
        """Set the camera's exposure, if it can be set, before ``led`` is lit."""
        if exposure_control is not None:
            with _step(BurstStep.EXPOSURE, led):
                exposure_control.set_exposure(exposure)

    def shoot(step: BurstStep, led: int, exposure: float, code: int) -> CapturedFrame:
        """Light ``led`` alone, wait for the acknowledgement, grab its frame as ``step``."""
        expose(exposure, led)
        with _step(BurstStep.SWITCH, led):
            acked = board.set_leds(1 << led)
        if acked != 1 << led:
            raise _StepFailedError(
                BurstStep.SWITCH, led, f"board acknowledged mask {acked:#x}, not {1 << led:#x}")
        stamp = clock()
        image = _grab(camera, step, led, exposure + grab_timeout_s, shape, dtype)
        return CapturedFrame(led, image, stamp, exposure, code / MAX_LEVEL)

    start = time.monotonic()
    try:
        for led, code in programmed.items():
            with _step(BurstStep.LEVEL, led):
                board.set_level(led, code)
        frames = [shoot(BurstStep.GRAB, *entry)
                  for entry in zip(order, exposures, codes, strict=True)]
        repeat = (shoot(BurstStep.REPEAT, order[0], exposures[0], codes[0]) if repeat_first
                  else None)
        with _step(BurstStep.OFF, None):
            board.all_off()
        dark = None
        if with_dark:
            exposure = max(exposures)
            expose(exposure, None)
            stamp = clock()
            image = _grab(camera, BurstStep.DARK, None, exposure + grab_timeout_s, shape, dtype)
            dark = CapturedFrame(DARK_LED, image, stamp, exposure, 0.0)
    except _StepFailedError as exc:
        with suppress(FingerpsDriverError):
            board.all_off()
        reason = f"burst {burst_id} failed at {exc}"
        return BurstResult(burst_id, (), None, False, reason, time.monotonic() - start,
                           failed_step=exc.step, error_type=exc.error_type)
    return BurstResult(burst_id, tuple(frames), dark, True, "", time.monotonic() - start,
                       repeat=repeat)


def _grab(
    camera: Camera,
    step: BurstStep,
    led: int | None,
    timeout_s: float,
    shape: tuple[int, ...],
    dtype: np.dtype | None,
) -> np.ndarray:
    """Grab one frame and check it; raise ``_StepFailedError`` naming ``step`` and ``led``."""
    with _step(step, led):
        image = camera.grab(timeout_s=timeout_s)
    if not isinstance(image, np.ndarray):
        raise _StepFailedError(step, led, f"camera returned {type(image).__name__}, not an image")
    if image.shape != shape:
        raise _StepFailedError(
            step, led,
            f"frame of shape {image.shape}, expected {shape}; check the camera's resolution",
        )
    if dtype is not None and image.dtype != dtype:
        raise _StepFailedError(
            step, led, f"frame of dtype {image.dtype}, expected {dtype} for {camera.encoding}"
        )
    return image
