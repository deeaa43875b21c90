"""recon_node's output messages built from a reconstruction, without a node
(``reconstruction.outputs``): topics in publishing order, the burst's header, encodings, the
normals turned into the optical frame, the normal map of the enhanced normals, the points,
each message built only when asked for; and the fingerprint's message."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import Reconstruction
from fingerps_recon.reconstruction import outputs
from fingerps_recon.reconstruction.outputs import (
    OUTPUT_TOPICS,
    fingerprint_message,
    output_messages,
)
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array
from fingerps_ros.point_cloud_conversion import cloud_to_points

HEADER = Header(stamp=Time(sec=12, nanosec=34), frame_id="fingerps_camera_optical_frame")


def reconstruction(*, enhanced: bool) -> Reconstruction:
    """A 4x5 result: a tilted plane on the left three columns."""
    rng = np.random.default_rng(3)
    mask = np.zeros((4, 5), bool)
    mask[:, :3] = True
    normals = np.where(mask[..., None], np.float32([0.6, 0.0, 0.8]), 0).astype(np.float32)
    depth = np.where(mask, 0.09, np.nan).astype(np.float32)
    points = rng.uniform(-0.01, 0.01, (int(mask.sum()), 3)).astype(np.float32)
    return Reconstruction(
        normals_ps=normals, enhanced_ps=normals[:, ::-1].copy() if enhanced else None,
        albedo=np.where(mask, 0.5, 0).astype(np.float32), mask=mask, depth_m=depth,
        height_m=depth, points_optical=points, point_albedo=np.full(len(points), 0.5,
                                                                    np.float32))


@pytest.mark.parametrize("enhanced", [True, False])
def test_the_outputs_in_order_with_the_bursts_header(enhanced: bool) -> None:
    result = reconstruction(enhanced=enhanced)
    made = list(output_messages(result, HEADER))
    assert [o.topic for o in made] == list(OUTPUT_TOPICS) == [
        topics.POINTS, topics.NORMALS, topics.DEPTH, topics.ALBEDO, topics.NORMAL_MAP]
    assert all(o.message.header == HEADER for o in made)
    by_topic = {o.topic: o for o in made}
    normals = by_topic[topics.NORMALS]
    assert normals.message.encoding == normals.encoding == "32FC3"
    np.testing.assert_array_equal(image_to_array(normals.message),
                                  result.normals_ps * np.float32([1, -1, -1]))
    shown = result.enhanced_ps if enhanced else result.normals_ps
    normal_map = by_topic[topics.NORMAL_MAP]
    assert normal_map.message.encoding == normal_map.encoding == "rgb8"
    np.testing.assert_array_equal(normal_map.array, normal_map_rgb(shown, mask=result.mask))
    np.testing.assert_array_equal(image_to_array(normal_map.message), normal_map.array)
    for topic, array in ((topics.DEPTH, result.depth_m), (topics.ALBEDO, result.albedo)):
        assert by_topic[topic].encoding == by_topic[topic].message.encoding == "32FC1"
        assert by_topic[topic].array is array
        np.testing.assert_array_equal(image_to_array(by_topic[topic].message), array)
    points, intensity = cloud_to_points(by_topic[topics.POINTS].message)
    np.testing.assert_array_equal(points, result.points_optical)
    np.testing.assert_array_equal(intensity, result.point_albedo)
    assert by_topic[topics.POINTS].array is None


def test_each_output_is_built_only_when_asked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[int] = []
    monkeypatch.setattr(outputs, "normal_map_rgb",
                        lambda n, *, mask: drawn.append(1) or normal_map_rgb(n, mask=mask))
    made = output_messages(reconstruction(enhanced=True), HEADER)
    assert [next(made).topic for _ in range(4)] == [
        topics.POINTS, topics.NORMALS, topics.DEPTH, topics.ALBEDO] and not drawn
    assert next(made).topic == topics.NORMAL_MAP and drawn == [1]


def test_only_the_outputs_asked_for_are_built(monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[int] = []
    monkeypatch.setattr(outputs, "normal_map_rgb",
                        lambda n, *, mask: drawn.append(1) or normal_map_rgb(n, mask=mask))
    made = list(output_messages(reconstruction(enhanced=True), HEADER,
                                (topics.POINTS, topics.DEPTH)))
    assert [o.topic for o in made] == [topics.POINTS, topics.DEPTH] and not drawn
    assert list(output_messages(reconstruction(enhanced=True), HEADER, ())) == []


def test_the_fingerprint_message_is_mono8_in_the_prints_frame() -> None:
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    msg = fingerprint_message(image, HEADER.stamp)
    assert msg.encoding == "mono8" and msg.header.stamp == HEADER.stamp
    assert msg.header.frame_id == topics.FINGERPRINT_FRAME
    np.testing.assert_array_equal(image_to_array(msg), image)
