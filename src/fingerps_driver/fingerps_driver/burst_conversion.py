"""A captured burst as messages: a TaggedFrame per frame, the Burst, the stamped CameraInfo.

The frames of ``fingerps_driver.capture.burst`` become ``TaggedFrame``s (header stamped
with the board's acknowledgement, the LED, exposure and level); the ``Burst`` holds them in
LED order (Burst.msg) with the dark and repeated frames, and the CameraInfo stamped like
its last frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_driver.capture.burst import BurstResult, CapturedFrame
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_ros.image_conversion import array_to_image
from fingerps_ros.time_conversion import time_message


def tagged_frame(frame: CapturedFrame, *, burst_id: int, led_count: int, encoding: str,
                 frame_id: str) -> TaggedFrame:
    """``frame`` as a TaggedFrame of burst ``burst_id``, its image in ``encoding``."""
    header = Header(stamp=time_message(frame.stamp_ns), frame_id=frame_id)
    return TaggedFrame(
        header=header, burst_id=burst_id, led_index=frame.led_index, led_count=led_count,
        exposure_time=frame.exposure_s, led_intensity=frame.level,
        image=array_to_image(frame.image, encoding=encoding, header=header))


def stamped_camera_info(current: CameraInfo, header: Header) -> CameraInfo:
    """A copy of ``current`` (the calibration in force) with ``header``."""
    return CameraInfo(header=header, width=current.width, height=current.height,
                      distortion_model=current.distortion_model, d=current.d,
                      k=current.k, r=current.r, p=current.p)


def burst_message(result: BurstResult, tagged: Sequence[TaggedFrame], camera_info: CameraInfo,
                  tag: Callable[[CapturedFrame], TaggedFrame]) -> Burst:
    """The Burst of ``result``: ``tagged`` (its frames in capture order) sorted by LED,
    ``camera_info``, and the dark and repeated frames tagged with ``tag``."""
    by_led = sorted(tagged, key=lambda f: f.led_index)  # Burst.msg: frames in LED order
    burst = Burst(header=tagged[-1].header, burst_id=result.burst_id, frames=by_led,
                  camera_info=camera_info)
    if result.dark is not None:
        burst.has_dark_frame = True
        burst.dark_frame = tag(result.dark)
    if result.repeat is not None:
        burst.has_repeat_frame = True
        burst.repeat_frame = tag(result.repeat)
    return burst
