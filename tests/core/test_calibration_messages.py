"""Tests of fingerps_calib.calibration_messages: calib_node's frames in, calibrations out."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image

from fingerps_calib.calibration_messages import (
    burst_shots,
    driver_camera_info,
    flat_field_message,
    lights_message,
    request_shots,
)
from fingerps_calib.calibration_store import FlatFieldRecord, LightsRecord
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.led_triangulation import Placement, combine_placements
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_ros.image_conversion import array_to_image, image_to_array

STAMP = 1_760_000_000_123_456_789
K = np.array([[3000.0, 0.0, 329.0], [0.0, 3000.0, 246.0], [0.0, 0.0, 1.0]])


def _frame(k: int, image: np.ndarray, *, count: int = 3, encoding: str = "mono8",
           frame_id: str = "cam") -> TaggedFrame:
    frame = TaggedFrame(burst_id=1, led_index=k, led_count=count,
                        image=array_to_image(image, encoding=encoding))
    frame.header.frame_id = frame_id
    return frame


def _camera_info() -> CameraInfo:
    info = CameraInfo(width=640, height=480, distortion_model="plumb_bob", d=[0.0] * 5,
                      k=[float(x) for x in K.ravel()])
    info.header.frame_id = "fingerps_camera_optical_frame"
    return info


def test_request_frames_become_shots_in_led_order_with_their_dark_frame():
    images = [np.full((4, 5), 10 * (k + 1), np.uint8) for k in range(3)]
    dark = _frame(TaggedFrame.LED_DARK, np.full((4, 5), 2, np.uint8))
    shots = request_shots([_frame(2, images[2]), dark, _frame(0, images[0]),
                           _frame(1, images[1])], _camera_info())
    np.testing.assert_array_equal(shots.images, np.stack(images))
    np.testing.assert_array_equal(shots.dark, np.full((4, 5), 2, np.uint8))
    assert shots.encoding == "mono8" and shots.frame_id == "cam"
    assert shots.camera_info.width == 640 and shots.camera_info.height == 480
    assert shots.camera_info.frame_id == "fingerps_camera_optical_frame"
    without = request_shots([_frame(k, im) for k, im in enumerate(images)], None)
    assert without.dark is None and without.camera_info is None


def test_a_burst_becomes_shots():
    images = [np.full((4, 5), 1000 * (k + 1), np.uint16) for k in range(3)]
    burst = Burst(frames=[_frame(k, im, encoding="mono16") for k, im in
                          reversed(list(enumerate(images)))],
                  has_dark_frame=True, camera_info=_camera_info(),
                  dark_frame=_frame(TaggedFrame.LED_DARK, np.zeros((4, 5), np.uint16),
                                    encoding="mono16"))
    shots = burst_shots(burst)
    np.testing.assert_array_equal(shots.images, np.stack(images))
    assert shots.encoding == "mono16" and shots.dark.shape == (4, 5)
    np.testing.assert_array_equal(shots.camera_info.k, K.ravel())
    burst.has_dark_frame = False
    assert burst_shots(burst).dark is None


@pytest.mark.parametrize(("frames", "expected"), [
    ([], "expected one frame per LED 0..0, got LEDs []: capture a whole burst"),
    ([_frame(0, np.zeros((4, 4), np.uint8)), _frame(2, np.zeros((4, 4), np.uint8))],
     "expected one frame per LED 0..2, got LEDs [0, 2]"),
    ([_frame(k, np.zeros((4, 4 + k), np.uint8), count=2) for k in range(2)],
     "frames of different sizes [(4, 4), (4, 5)]; recapture"),
    ([_frame(k, np.zeros((4, 4, 3), np.uint8), count=2, encoding="rgb8") for k in range(2)],
     "frames are rgb8; the calibration needs mono8, mono16 or 32FC1 images"),
])
def test_frames_that_make_no_burst_are_refused(frames, expected):
    with pytest.raises(FingerpsCalibError) as caught:
        request_shots(frames, None)
    assert str(caught.value).startswith(expected), caught.value


def test_a_bad_image_is_refused_naming_its_led():
    broken = _frame(1, np.zeros((4, 4), np.uint8), count=2)
    broken.image = Image(height=4, width=4, encoding="mono8", step=4, data=b"\0" * 3)
    with pytest.raises(FingerpsCalibError, match=r"^LED 1: image 4x4 mono8"):
        request_shots([_frame(0, np.zeros((4, 4), np.uint8), count=2), broken], None)


def test_camera_info_values():
    info = driver_camera_info(_camera_info())
    np.testing.assert_array_equal(info.k, K.ravel())
    np.testing.assert_array_equal(info.d, np.zeros(5))
    assert (info.distortion_model, info.width, info.height) == ("plumb_bob", 640, 480)
    assert driver_camera_info(CameraInfo()).frame_id == ""


def _lights_record(placements: int) -> LightsRecord:
    leds = np.array([[0.040, 0.005, 0.001], [-0.020, 0.035, -0.002], [-0.030, -0.028, 0.0]])
    made = []
    for centre in [(0.002, -0.0015, 0.094), (-0.0055, 0.002, 0.094)][:placements]:
        c = np.asarray(centre)
        origins = c + 0.004 * np.array([[0.1, 0.0, -1.0], [0.0, 0.1, -1.0], [-0.1, 0.0, -1.0]])
        directions = leds - origins
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        made.append(Placement(c, 0.004, 0.1, origins, directions,
                              np.array([[300.5, 200.25]] * 3), np.array([0.05, 0.02, 0.04])))
    lights = combine_placements(made, reference_point_optical_m=np.array([0.0, 0.0025, 0.09]))
    assert lights.ok, lights.problems
    return LightsRecord(camera_name="rig_2", frame_id="cam", stamp_ns=STAMP, image_width=640,
                        image_height=480, camera_matrix=K, lights=lights)


def test_a_light_calibration_message():
    record = _lights_record(2)
    msg = lights_message(record, [1.0, 0.5, 0.25])
    assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == (
        "cam", 1_760_000_000, 123_456_789)
    assert msg.camera_name == "rig_2" and msg.placements == 2
    np.testing.assert_allclose([[d.x, d.y, d.z] for d in msg.directions],
                               record.lights.directions_optical)
    np.testing.assert_allclose([[p.x, p.y, p.z] for p in msg.led_positions],
                               record.lights.led_positions_optical_m)
    assert list(msg.relative_intensities) == [1.0, 0.5, 0.25]
    np.testing.assert_allclose(msg.residuals, [0.05, 0.02, 0.04])
    assert msg.sphere_radius == 0.004 and msg.edge_fit_residual == pytest.approx(0.1)
    assert msg.sphere_center.z == pytest.approx(0.094)
    assert len(lights_message(_lights_record(1), [1.0] * 3).led_positions) == 0


def test_a_flat_field_message():
    portions = np.linspace(0.5, 1.0, 3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)
    record = FlatFieldRecord(camera_name="rig_2", frame_id="cam", stamp_ns=STAMP,
                             portions=portions, relative_intensities=np.array([1.0, 0.9, 0.8]),
                             fit_residuals=np.zeros(3), polynomial_degree=4)
    msg = flat_field_message(record)
    assert msg.header.stamp.nanosec == 123_456_789 and msg.camera_name == "rig_2"
    assert [m.encoding for m in msg.maps] == ["32FC1"] * 3
    assert all(m.header == msg.header for m in msg.maps)
    np.testing.assert_array_equal(np.stack([image_to_array(m) for m in msg.maps]), portions)
    assert list(msg.relative_intensities) == [1.0, 0.9, 0.8]
