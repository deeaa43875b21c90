"""Burst, LightCalibration and FlatField messages checked on arrival and turned into the
arrays ``fingerps_recon.photometric.pipeline`` takes.

Every check reads the messages' fields before it touches their pixels, so a burst beyond the
size bounds (:class:`BurstLimits`) is refused cheaply, in the subscription callback; every
refusal is a ``FingerpsReconError`` (:class:`IncompleteBurstError` for a missing LED) that
says what to do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sensor_msgs.msg import Image

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon.errors import FingerpsReconError, IncompleteBurstError
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.full_scale import FULL_SCALE, MONO16_DEFAULT, full_scale_of
from fingerps_recon.photometric.pipeline import check_calibration, check_portions
from fingerps_recon.scan.scan_sequence import ScanBurst
from fingerps_ros.image_conversion import image_to_array, images_to_array


@dataclass(frozen=True)
class BurstLimits:
    """Bounds on what a burst may carry (parameters max_image_width, max_image_height,
    max_burst_frames of recon_node)."""

    max_width: int = 4096
    max_height: int = 4096
    max_frames: int = 16


@dataclass(frozen=True)
class BurstInputs:
    """A burst's arrays as ``pipeline.reconstruct_prepared`` takes them."""

    images: np.ndarray            # (K, H, W) in LED order, as captured
    full_scale: float             # largest grey level of the images' encoding
    dark: np.ndarray | None       # (H, W) the burst's dark frame
    camera_matrix: np.ndarray     # (3, 3) K of the burst's camera_info


def check_burst_size(burst: Burst, limits: BurstLimits) -> None:
    """Raise ``FingerpsReconError`` if a burst carries more frames than ``limits`` allow, or
    an image (a frame, the dark or repeat frame) of no pixels or beyond the size bounds.
    Reads the messages' fields only: cheap enough for the subscription callback."""
    if len(burst.frames) > limits.max_frames:
        raise FingerpsReconError(
            f"{len(burst.frames)} frames, more than max_burst_frames {limits.max_frames}: "
            "refused; raise max_burst_frames if the rig really has that many LEDs")
    images = [f.image for f in burst.frames]
    images += [burst.dark_frame.image] if burst.has_dark_frame else []
    images += [burst.repeat_frame.image] if burst.has_repeat_frame else []
    for image in images:
        _check_image_size(image, limits, "image")


def burst_inputs(burst: Burst, led_count: int, *, mono16_full_scale: float = MONO16_DEFAULT,
                 limits: BurstLimits | None = None) -> BurstInputs:
    """The arrays of a Burst message for a calibration of ``led_count`` LEDs; raises
    ``FingerpsReconError`` on a burst beyond ``limits`` (:func:`check_burst_size`), a
    missing LED (:class:`IncompleteBurstError`), mixed or colour images, a dark frame of
    another encoding or size, or a camera_info without intrinsics."""
    check_burst_size(burst, limits or BurstLimits())
    images, encoding = burst_images(burst, led_count)
    full_scale = full_scale_of(encoding, mono16_full_scale=mono16_full_scale)
    dark = None
    if burst.has_dark_frame:
        image = burst.dark_frame.image
        if image.encoding != encoding or (image.height, image.width) != images.shape[1:]:
            raise FingerpsReconError(
                f"the dark frame is {image.width}x{image.height} {image.encoding} but the "
                f"images are {images.shape[2]}x{images.shape[1]} {encoding}: it must come "
                "from the same camera mode")
        dark = image_to_array(image)
    k_matrix = np.asarray(burst.camera_info.k, dtype=np.float64).reshape(3, 3)
    if not k_matrix[0, 0] > 0:
        raise FingerpsReconError("the burst's camera_info has no intrinsics (fx <= 0)")
    return BurstInputs(images, full_scale, dark, k_matrix)


def burst_images(burst: Burst, led_count: int) -> tuple[np.ndarray, str]:
    """The burst's images as (K, H, W) in LED order and their encoding; or an error saying
    what is wrong (a missing LED, mixed sizes or encodings, colour images)."""
    frames = sorted(burst.frames, key=lambda f: f.led_index)
    indices = [f.led_index for f in frames]
    if indices != list(range(led_count)):
        missing = sorted(set(range(led_count)) - set(indices))
        raise IncompleteBurstError(
            f"LEDs {indices} instead of 0..{led_count - 1}"
            + (f" (missing {missing})" if missing else "")
            + ": not reconstructed; the driver must publish whole bursts, or recalibrate if "
            "the LED count changed")
    encodings = {f.image.encoding for f in frames}
    sizes = {(f.image.height, f.image.width) for f in frames}
    if len(encodings) != 1 or len(sizes) != 1:
        raise FingerpsReconError(
            f"the burst mixes image encodings {sorted(encodings)} or sizes {sorted(sizes)}; "
            "every frame of a burst must come from one camera mode")
    encoding = encodings.pop()
    if encoding not in FULL_SCALE:
        raise FingerpsReconError(
            f"the burst's images are {encoding}; photometric stereo needs one grey level per "
            f"pixel: set the camera's pixel format to {' or '.join(FULL_SCALE)}")
    return images_to_array([f.image for f in frames]), encoding


def calibration_arrays(lights: LightCalibration) -> tuple[
        np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Directions (K, 3) in the PS frame, relative intensities (K,) or None, LED positions
    (K, 3) in the optical frame or None, from a LightCalibration message."""
    directions = np.array([[d.x, d.y, d.z] for d in lights.directions],
                          dtype=np.float64).reshape(-1, 3)
    intensities = np.asarray(lights.relative_intensities, dtype=np.float64)
    leds = np.array([[p.x, p.y, p.z] for p in lights.led_positions],
                    dtype=np.float64).reshape(-1, 3)
    return (optical_to_ps(directions), intensities if intensities.size else None,
            leds if len(leds) else None)


def check_light_calibration(lights: LightCalibration) -> LightCalibration:
    """``lights``, checked: raise ``FingerpsReconError`` unless the message can determine
    normals (finite, unit, non-degenerate directions; finite positive intensities; finite LED
    positions, one per direction): ``pipeline.check_calibration`` on its arrays."""
    directions, intensities, leds = calibration_arrays(lights)
    check_calibration(directions, intensities=intensities, led_positions_optical=leds)
    return lights


def flat_field_maps(flat: FlatField, limits: BurstLimits) -> np.ndarray:
    """The portion maps (K, H, W) float32 of a FlatField message, or ``FingerpsReconError``
    if there are none or too many, they are not single-channel maps of one size within
    ``limits``, or not finite and positive (``pipeline.check_portions``)."""
    if not 1 <= len(flat.maps) <= limits.max_frames:
        raise FingerpsReconError(
            f"{len(flat.maps)} flat-field maps: give one per LED (at most max_burst_frames "
            f"{limits.max_frames})")
    for image in flat.maps:
        _check_image_size(image, limits, "flat-field map")
    maps = images_to_array(flat.maps)
    if maps.ndim != 3:
        raise FingerpsReconError(
            f"flat-field maps of {flat.maps[0].encoding}: they must have one channel (32FC1)")
    maps = maps.astype(np.float32, copy=False)
    check_portions(maps)
    return maps


def _check_image_size(image: Image, limits: BurstLimits, what: str) -> None:
    width, height = int(image.width), int(image.height)
    if width < 1 or height < 1:
        raise FingerpsReconError(
            f"an {what} of {width}x{height} px: empty; check the camera's publisher")
    if width > limits.max_width or height > limits.max_height:
        raise FingerpsReconError(
            f"an {what} of {width}x{height} px, beyond max_image_width x max_image_height "
            f"{limits.max_width}x{limits.max_height}: refused; raise the bounds if the "
            "camera really is that large (memory and time grow with the pixels)")


def scan_burst(burst: Burst, *, mono16_full_scale: float = MONO16_DEFAULT) -> ScanBurst:
    """A Burst message (from the driver's capture_burst) as the arrays the Scan sequence
    looks at (``scan.scan_sequence.ScanBurst``: the first LED's frame, the dark frame, the
    repeat of the first LED and its first frame; None where the burst has none)."""
    encoding = burst.frames[0].image.encoding if burst.frames else ""
    led = burst.repeat_frame.led_index
    repeated = next((f for f in burst.frames if f.led_index == led), None)
    has_repeat = burst.has_repeat_frame
    return ScanBurst(
        burst.burst_id, image_to_array(burst.frames[0].image) if burst.frames else None,
        image_to_array(burst.dark_frame.image) if burst.has_dark_frame else None,
        full_scale_of(encoding, mono16_full_scale=mono16_full_scale),
        repeated=image_to_array(repeated.image) if has_repeat and repeated else None,
        repeat=image_to_array(burst.repeat_frame.image) if has_repeat else None,
        repeat_led=led, source=burst)
