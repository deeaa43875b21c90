"""calib_node's message conversions: frames and camera_info in, calibrations out.

TaggedFrame lists (a request's frames or a driver's Burst) become `Shots` (the images
stacked in LED order, as arrays) and a CameraInfo a `DriverCameraInfo`; a light
calibration or a flat field in force becomes its LightCalibration or FlatField message.
Frames that cannot make a burst (LEDs missing, sizes or encodings that differ) are refused
here, with a message saying what to send.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from geometry_msgs.msg import Point, Vector3
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_calib.calibration_camera import DriverCameraInfo
from fingerps_calib.calibration_keeper import Shots
from fingerps_calib.calibration_store import FlatFieldRecord, LightsRecord
from fingerps_calib.errors import FingerpsCalibError
from fingerps_msgs.msg import Burst, FlatField, LightCalibration, TaggedFrame
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image, image_to_array
from fingerps_ros.time_conversion import time_message


def frame_pixels(frame: TaggedFrame) -> np.ndarray:
    """The pixels of ``frame`` (H, W); a bad image is refused naming its LED."""
    try:
        return image_to_array(frame.image)
    except FingerpsError as exc:
        raise FingerpsCalibError(f"LED {frame.led_index}: {exc}") from exc


def request_shots(frames: Sequence[TaggedFrame], camera_info: CameraInfo | None) -> Shots:
    """The `Shots` of a request's frames (the lit ones in LED order, the first dark one).

    ``camera_info`` is the driver's latest, if calib_node has one.
    """
    lit = [f for f in frames if f.led_index != TaggedFrame.LED_DARK]
    darks = [frame_pixels(f) for f in frames if f.led_index == TaggedFrame.LED_DARK]
    return _shots(sorted(lit, key=lambda f: f.led_index), camera_info,
                  darks[0] if darks else None)


def burst_shots(burst: Burst) -> Shots:
    """The `Shots` of a driver's burst (its dark frame, if it has one)."""
    dark = frame_pixels(burst.dark_frame) if burst.has_dark_frame else None
    return _shots(sorted(burst.frames, key=lambda f: f.led_index), burst.camera_info, dark)


def stack_frames(frames: Sequence[TaggedFrame]) -> np.ndarray:
    """(K, H, W) images of one frame per LED 0..K-1 (``frames`` in LED order).

    Raises
    ------
    FingerpsCalibError
        LEDs missing, frames of different sizes, colour images.
    """
    indices = [f.led_index for f in frames]
    count = frames[0].led_count if frames else 0
    if not frames or indices != list(range(count)):
        raise FingerpsCalibError(
            f"expected one frame per LED 0..{max(count - 1, 0)}, got LEDs {indices}: "
            "capture a whole burst")
    images = [frame_pixels(f) for f in frames]
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise FingerpsCalibError(f"frames of different sizes {sorted(shapes)}; recapture")
    if images[0].ndim != 2:
        raise FingerpsCalibError(
            f"frames are {frames[0].image.encoding}; the calibration needs mono8, mono16 "
            "or 32FC1 images")
    return np.stack(images)


def driver_camera_info(info: CameraInfo) -> DriverCameraInfo:
    """The values of a sensor_msgs/CameraInfo calib_node uses."""
    return DriverCameraInfo(
        k=np.asarray(info.k, dtype=np.float64), d=np.asarray(info.d, dtype=np.float64),
        distortion_model=str(info.distortion_model), width=int(info.width),
        height=int(info.height), frame_id=str(info.header.frame_id))


def lights_message(record: LightsRecord, relative_intensities: Sequence[float]
                   ) -> LightCalibration:
    """The LightCalibration message of a light calibration and its relative intensities."""
    lights = record.lights
    header = _header(record.frame_id, record.stamp_ns)
    centre = lights.sphere_center_optical_m
    return LightCalibration(
        header=header, camera_name=record.camera_name,
        directions=[Vector3(x=float(d[0]), y=float(d[1]), z=float(d[2]))
                    for d in lights.directions_optical],
        relative_intensities=[float(x) for x in relative_intensities],
        residuals=[float(r) for r in lights.residuals_px],
        sphere_radius=float(lights.placements[-1].radius_m),
        sphere_center=Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2])),
        edge_fit_residual=float(lights.edge_rms_px),
        placements=len(lights.placements),
        led_positions=[Point(x=float(q[0]), y=float(q[1]), z=float(q[2]))
                       for q in lights.led_positions_optical_m])


def flat_field_message(record: FlatFieldRecord) -> FlatField:
    """The FlatField message of a flat field (its maps as 32FC1 images)."""
    header = _header(record.frame_id, record.stamp_ns)
    return FlatField(
        header=header, camera_name=record.camera_name,
        maps=[array_to_image(m, encoding="32FC1", header=header) for m in record.portions],
        relative_intensities=[float(x) for x in record.relative_intensities])


def _shots(frames: list[TaggedFrame], camera_info: CameraInfo | None,
           dark: np.ndarray | None) -> Shots:
    images = stack_frames(frames)
    return Shots(images=images, encoding=frames[0].image.encoding,
                 frame_id=frames[0].header.frame_id, dark=dark,
                 camera_info=driver_camera_info(camera_info) if camera_info is not None
                 else None)


def _header(frame_id: str, stamp_ns: int) -> Header:
    return Header(frame_id=frame_id, stamp=time_message(stamp_ns))
