"""Round trips of the message conversions (numpy <-> sensor_msgs) and of fingerps_msgs
through rclpy's CDR serialisation, as they travel between the nodes."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Vector3
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from fingerps_msgs.msg import Burst, LightCalibration, TaggedFrame
from fingerps_ros.errors import MessageError
from fingerps_ros.image_conversion import array_to_image, image_to_array
from fingerps_ros.point_cloud_conversion import cloud_to_points, points_to_cloud

H, W = 5, 7  # odd sizes, so a row is no multiple of 2, 4 or 8 bytes in 8-bit encodings


def _header() -> Header:
    return Header(stamp=Time(sec=1_700_000_000, nanosec=123_456_789),
                  frame_id="fingerps_camera_optical_frame")


def _random(encoding: str, rng: np.random.Generator) -> np.ndarray:
    if encoding == "mono8":
        return rng.integers(0, 256, (H, W), dtype=np.uint8)
    if encoding == "mono16":
        return rng.integers(0, 65536, (H, W), dtype=np.uint16)
    if encoding == "rgb8":
        return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    if encoding == "32FC1":
        return rng.normal(size=(H, W)).astype(np.float32)
    return rng.normal(size=(H, W, 3)).astype(np.float32)


@pytest.mark.parametrize(("encoding", "dtype", "shape", "step"), [
    ("mono8", np.uint8, (H, W), W),
    ("mono16", np.uint16, (H, W), 2 * W),
    ("rgb8", np.uint8, (H, W, 3), 3 * W),
    ("32FC1", np.float32, (H, W), 4 * W),
    ("32FC3", np.float32, (H, W, 3), 12 * W),
])
def test_image_round_trip(encoding: str, dtype: type, shape: tuple[int, ...],
                          step: int) -> None:
    array = _random(encoding, np.random.default_rng(len(encoding)))
    original = array.copy()
    msg = array_to_image(array, encoding=encoding, header=_header())
    assert (msg.height, msg.width, msg.encoding, msg.step) == (H, W, encoding, step)
    assert msg.is_bigendian == 0 and len(msg.data) == step * H
    assert msg.header == _header()
    back = image_to_array(msg)
    assert back.dtype == np.dtype(dtype) and back.shape == shape
    np.testing.assert_array_equal(back, original)
    # A new, writable array that does not share the message's buffer.
    back[...] = 0
    np.testing.assert_array_equal(image_to_array(msg), original)
    np.testing.assert_array_equal(array, original)


def test_float64_input_is_stored_as_float32() -> None:
    array = np.linspace(0.0, 1.0, H * W).reshape(H, W)  # float64
    back = image_to_array(array_to_image(array, encoding="32FC1"))
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, array, rtol=1e-7)


def test_padded_rows_are_unpadded() -> None:
    array = _random("rgb8", np.random.default_rng(1))
    row = 3 * W
    step = row + 5  # padding bytes after every row, filled with junk
    data = np.full((H, step), 0xAB, dtype=np.uint8)
    data[:, :row] = array.reshape(H, row)
    msg = Image(height=H, width=W, encoding="rgb8", is_bigendian=0, step=step,
                data=data.tobytes())
    np.testing.assert_array_equal(image_to_array(msg), array)


def test_big_endian_mono16() -> None:
    array = np.array([[0x0102, 0x0FFF, 0xFF00], [1, 256, 65535]], dtype=np.uint16)
    msg = Image(height=2, width=3, encoding="mono16", is_bigendian=1, step=6,
                data=array.astype(">u2").tobytes())
    back = image_to_array(msg)
    assert back.dtype == np.uint16 and back.dtype.isnative
    np.testing.assert_array_equal(back, array)
    # The same bytes read as little-endian would swap them: the flag is what decides.
    msg.is_bigendian = 0
    np.testing.assert_array_equal(image_to_array(msg), array.byteswap())


@pytest.mark.parametrize(("step", "missing"), [(W, 1), (W - 1, 0)],
                         ids=["data_too_short", "step_too_short"])
def test_too_little_data_is_refused(step: int, missing: int) -> None:
    msg = Image(height=H, width=W, encoding="mono8", step=step,
                data=bytes(step * H - missing))
    with pytest.raises(MessageError, match="too few"):
        image_to_array(msg)


def test_unsupported_encodings_are_refused() -> None:
    with pytest.raises(MessageError, match="bayer_rggb8"):
        array_to_image(np.zeros((H, W), np.uint8), encoding="bayer_rggb8")
    msg = Image(height=H, width=W, encoding="yuv422", step=2 * W, data=bytes(2 * W * H))
    with pytest.raises(MessageError, match="yuv422"):
        image_to_array(msg)
    with pytest.raises(MessageError, match="3 channel"):
        array_to_image(np.zeros((H, W), np.uint8), encoding="rgb8")


def test_point_cloud_round_trip() -> None:
    rng = np.random.default_rng(2)
    points = (rng.normal(0.0, 0.01, (11, 3)) + np.array([0.0, 0.0, 0.09])).astype(np.float32)
    intensity = rng.uniform(0.0, 1.0, 11).astype(np.float32)
    cloud = points_to_cloud(points, intensity, header=_header())
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity"]
    assert all(f.datatype == PointField.FLOAT32 and f.count == 1 for f in cloud.fields)
    assert [f.offset for f in cloud.fields] == [0, 4, 8, 12]
    assert (cloud.height, cloud.width, cloud.point_step, cloud.row_step) == (1, 11, 16, 176)
    assert len(cloud.data) == 176 and cloud.header == _header() and not cloud.is_bigendian
    # Through CDR too, as a subscriber receives it.
    received = deserialize_message(serialize_message(cloud), PointCloud2)
    back_points, back_intensity = cloud_to_points(received)
    assert back_points.dtype == np.float32 and back_points.shape == (11, 3)
    np.testing.assert_array_equal(back_points, points)
    np.testing.assert_array_equal(back_intensity, intensity)


def test_point_cloud_shapes_are_checked() -> None:
    with pytest.raises(MessageError, match=r"\(4, 2\)"):
        points_to_cloud(np.zeros((4, 2)), np.zeros(4), header=_header())
    with pytest.raises(MessageError, match=r"\(3,\)"):
        points_to_cloud(np.zeros((4, 3)), np.zeros(3), header=_header())
    cloud = points_to_cloud(np.zeros((4, 3)), np.zeros(4), header=_header())
    cloud.fields = cloud.fields[:3]
    with pytest.raises(MessageError, match="not x, y, z, intensity"):
        cloud_to_points(cloud)


def test_burst_survives_serialisation() -> None:
    rng = np.random.default_rng(3)
    header = _header()
    frames = [
        TaggedFrame(header=header, burst_id=42, led_index=k, led_count=2,
                    exposure_time=0.01, led_intensity=0.75,
                    image=array_to_image(_random("mono8", rng), encoding="mono8",
                                         header=header))
        for k in range(2)
    ]
    dark = TaggedFrame(header=header, burst_id=42, led_index=TaggedFrame.LED_DARK,
                       led_count=2, image=array_to_image(_random("mono8", rng),
                                                         encoding="mono8", header=header))
    info = CameraInfo(header=header, width=W, height=H, distortion_model="plumb_bob",
                      d=[0.0] * 5, k=[3000.0, 0.0, 3.0, 0.0, 3000.0, 2.0, 0.0, 0.0, 1.0])
    burst = Burst(header=header, burst_id=42, frames=frames, has_dark_frame=True,
                  dark_frame=dark, camera_info=info)

    back = deserialize_message(serialize_message(burst), Burst)
    assert back == burst
    assert [f.led_index for f in back.frames] == [0, 1]
    assert back.dark_frame.led_index == 255 and back.has_dark_frame
    for sent, received in zip(burst.frames, back.frames, strict=True):
        np.testing.assert_array_equal(image_to_array(received.image),
                                      image_to_array(sent.image))
    assert list(back.camera_info.k) == list(info.k)
    assert back.frames[1].led_intensity == pytest.approx(0.75)


def test_light_calibration_survives_serialisation() -> None:
    directions = np.array([[0.3, -0.2, -0.93], [-0.4, 0.1, -0.91], [0.0, 0.45, -0.89]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    msg = LightCalibration(
        header=_header(), camera_name="fingerps_sim",
        directions=[Vector3(x=x, y=y, z=z) for x, y, z in directions],
        relative_intensities=[1.0, 0.93, 0.88], residuals=[0.01, 0.02, 0.03],
        sphere_radius=0.004, sphere_center=Point(x=0.002, y=-0.0015, z=0.094),
        edge_fit_residual=0.1)
    back = deserialize_message(serialize_message(msg), LightCalibration)
    assert back == msg
    np.testing.assert_array_equal([[d.x, d.y, d.z] for d in back.directions], directions)
    assert list(back.relative_intensities) == [1.0, 0.93, 0.88]
    assert back.sphere_center.z == 0.094 and back.camera_name == "fingerps_sim"
