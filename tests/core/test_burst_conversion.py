"""A captured burst as messages, without a node: the tags of each frame, the Burst's LED
order with its dark and repeated frames, the CameraInfo stamped with the burst."""

from __future__ import annotations

from functools import partial

import numpy as np
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from fingerps_driver.burst_conversion import (
    burst_message,
    stamped_camera_info,
    tagged_frame,
)
from fingerps_driver.capture.burst import DARK_LED, BurstResult, CapturedFrame
from fingerps_msgs.msg import TaggedFrame


def _frame(led: int, stamp_ns: int) -> CapturedFrame:
    return CapturedFrame(led, np.full((2, 3), led, np.uint8), stamp_ns, 0.01 * (led + 1),
                         0.5 if led != DARK_LED else 0.0)


def test_a_frame_is_tagged_with_its_led_exposure_and_level():
    msg = tagged_frame(_frame(2, 1_500_000_000), burst_id=9, led_count=7, encoding="mono8",
                       frame_id="cam")
    assert (msg.burst_id, msg.led_index, msg.led_count) == (9, 2, 7)
    assert (msg.exposure_time, msg.led_intensity) == (0.03, 0.5)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (
        1, 500_000_000, "cam")
    assert msg.image.header == msg.header
    assert (msg.image.width, msg.image.height, msg.image.encoding) == (3, 2, "mono8")
    assert bytes(msg.image.data) == bytes([2] * 6)


def test_the_burst_holds_its_frames_in_led_order_with_dark_and_repeat():
    frames = (_frame(4, 10), _frame(0, 20), _frame(2, 30))
    result = BurstResult(5, frames, _frame(DARK_LED, 50), True, "", 0.1,
                         repeat=_frame(4, 40))
    tag = partial(tagged_frame, burst_id=5, led_count=7, encoding="mono8", frame_id="cam")
    tagged = [tag(f) for f in frames]
    info = CameraInfo(width=3, height=2)
    burst = burst_message(result, tagged, info, tag)
    assert [f.led_index for f in burst.frames] == [0, 2, 4]
    assert burst.header == tagged[-1].header and burst.burst_id == 5
    assert burst.camera_info == info
    assert burst.has_dark_frame and burst.dark_frame.led_index == TaggedFrame.LED_DARK
    assert burst.has_repeat_frame and burst.repeat_frame.header.stamp.nanosec == 40
    plain = burst_message(BurstResult(6, frames, None, True, "", 0.1), tagged, info, tag)
    assert not plain.has_dark_frame and not plain.has_repeat_frame


def test_camera_info_is_copied_with_the_header():
    current = CameraInfo(width=3, height=2, distortion_model="plumb_bob", d=[0.1] * 5,
                         k=[1.0] * 9, r=[2.0] * 9, p=[3.0] * 12)
    header = Header(frame_id="cam")
    stamped = stamped_camera_info(current, header)
    assert stamped.header == header and current.header.frame_id == ""
    assert (stamped.width, stamped.height, stamped.distortion_model) == (3, 2, "plumb_bob")
    assert list(stamped.d) == [0.1] * 5 and list(stamped.k) == [1.0] * 9
    assert list(stamped.r) == [2.0] * 9 and list(stamped.p) == [3.0] * 12
