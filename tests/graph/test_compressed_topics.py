"""image_transport-style compressed companions over DDS (compressed_topics.py).

driver_node, calib_node and recon_node as separate processes on the simulated rig: recon
publishes, by default, ``normal_map/compressed``, ``fingerprint/compressed`` (PNG) and
``depth/compressedDepth`` beside the raw topics. Each compressed message, decoded with
OpenCV as any ROS subscriber would (the compressedDepth header read byte by byte), equals
the raw message of the same stamp: PNG exactly, depth within one quantization step. A
changed ``<base>.compressed.format`` applies to the next image. A bad
``<base>.enable_pub_plugins`` stops the node at start with the allowed values. The
companion is encoded only while subscribed, and a failure is counted, never raised.
``image_raw/compressed`` of driver_node (off by default): PNG exact for mono8 and mono16.
"""

from __future__ import annotations

import struct
from collections import defaultdict

import cv2
import numpy as np
import pytest
import rclpy
from polling import poll_until
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image
from stamps import stamp_key
from std_msgs.msg import Header

from fingerps_driver.demo import SPHERE_PLACEMENTS
from fingerps_msgs.srv import CalibrateLights, CaptureBurst
from fingerps_ros import compressed_topics, qos, topics
from fingerps_ros.compressed_topics import CompressedTopics
from fingerps_ros.image_compression import DepthQuantization, decode_compressed
from fingerps_ros.image_conversion import image_to_array
from fingerps_ros.parameters import ParameterChecks

NS = "/" + topics.NAMESPACE
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _capture(node: Node, call_service) -> None:
    """One capture_burst call of the test node, spun until answered; asserts success."""
    client = node.create_client(CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}")
    response = call_service(client, CaptureBurst.Request(), "a burst", timeout=60.0)
    assert response.success, response.message
    node.destroy_client(client)


def _store(node: Node, msg_type, topic: str, profile, into: dict) -> object:
    return node.create_subscription(
        msg_type, topic, lambda m: into.__setitem__(stamp_key(m.header), m), profile)


def _png(message: CompressedImage) -> np.ndarray:
    assert bytes(message.data[:8]) == PNG_SIGNATURE
    return cv2.imdecode(np.frombuffer(bytes(message.data), np.uint8), cv2.IMREAD_UNCHANGED)


def _depth_from_compressed_depth(message: CompressedImage) -> tuple[np.ndarray, float, float]:
    """compressed_depth_image_transport's decoder, written out: header, PNG, A / (q - B)."""
    data = bytes(message.data)
    kind, a, b = struct.unpack("<iff", data[:12])
    assert kind == 0  # INV_DEPTH
    q = cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert q.dtype == np.uint16
    with np.errstate(divide="ignore"):
        depth = np.where(q > 0, np.float32(a) / (q.astype(np.float32) - np.float32(b)),
                         np.nan)
    return depth.astype(np.float32), a, b


def test_recon_companions_equal_the_raw_outputs(ros_node: Node, start_node, spin_until,
                                                call_service, set_parameters,
                                                tmp_path) -> None:
    raw: dict[str, dict] = defaultdict(dict)
    packed: dict[str, dict] = defaultdict(dict)
    companions = {topics.NORMAL_MAP: "compressed", topics.FINGERPRINT: "compressed",
                  topics.DEPTH: "compressedDepth"}
    subscriptions = []
    for name, suffix in companions.items():
        _store(ros_node, Image, f"{NS}/{name}", qos.OUTPUT_QOS, raw[name])
        subscriptions.append(_store(ros_node, CompressedImage, f"{NS}/{name}/{suffix}",
                                    qos.OUTPUT_QOS, packed[name]))

    driver = start_node("fingerps_driver", "driver_node", "--ros-args",
                        "-p", "sim.scene:=sphere")
    calib = start_node("fingerps_calib", "calib_node", "--ros-args",
                       "-p", f"calibration_dir:={tmp_path / 'calibration'}")
    recon = start_node("fingerps_recon", "recon_node", "--ros-args",
                       "-p", "fingerprint:=true")  # companions: the defaults
    for process, name in ((driver, "driver"), (calib, "calib"), (recon, "recon")):
        process.wait_in_graph(ros_node, name, NS)
    # on by default: recon advertises the three companions
    spin_until(lambda: all(s.get_publisher_count() >= 1 for s in subscriptions),
               "recon's compressed publishers")

    def set_params(node_name: str, values: dict[str, object]) -> None:
        for result in set_parameters(node_name, values, timeout=60.0):
            assert result.successful, result.reason

    lights = ros_node.create_client(CalibrateLights, f"{NS}/calibrate_lights")
    for i, center in enumerate(SPHERE_PLACEMENTS):
        set_params("driver", {"sim.sphere_center": center})
        response = call_service(lights, CalibrateLights.Request(
            sphere_radius=0.004, add_placement=i > 0), f"light placement {i}", timeout=60.0)
        assert response.success, response.message
    set_params("driver", {"sim.scene": "finger"})

    def burst_out(keys_before: set) -> tuple[int, int]:
        """Capture until a burst's raw and compressed outputs have all arrived."""
        _capture(ros_node, call_service)

        def complete() -> tuple[int, int] | None:
            for key in set(packed[topics.NORMAL_MAP]) - keys_before:
                if all(key in raw[n] and key in packed[n] for n in companions):
                    return key
            return None
        spin_until(complete, "a burst's raw and compressed outputs", timeout=60.0)
        return complete()

    key = burst_out(set())
    # normal_map: rgb8 -> PNG of BGR, exact
    message = packed[topics.NORMAL_MAP][key]
    assert message.format == "rgb8; png compressed bgr8"
    assert message.header.frame_id == raw[topics.NORMAL_MAP][key].header.frame_id
    rgb = image_to_array(raw[topics.NORMAL_MAP][key])
    np.testing.assert_array_equal(cv2.cvtColor(_png(message), cv2.COLOR_BGR2RGB), rgb)
    # fingerprint: mono8 -> PNG, exact (format with upstream's trailing space)
    message = packed[topics.FINGERPRINT][key]
    assert message.format == "mono8; png compressed "
    assert message.header.frame_id == topics.FINGERPRINT_FRAME
    np.testing.assert_array_equal(_png(message), image_to_array(raw[topics.FINGERPRINT][key]))
    # depth: compressedDepth, within one quantization step
    message = packed[topics.DEPTH][key]
    assert message.format == "32FC1; compressedDepth png"
    depth = image_to_array(raw[topics.DEPTH][key])
    decoded, a, b = _depth_from_compressed_depth(message)
    quantization = DepthQuantization()
    assert (np.float32(a), np.float32(b)) == (quantization.a, quantization.b)
    finite = np.isfinite(depth)
    assert finite.sum() > 50_000
    np.testing.assert_array_equal(np.isfinite(decoded), finite)
    error = decoded[finite].astype(np.float64) - depth[finite]
    z = depth[finite].astype(np.float64)
    assert np.all(np.abs(error) <= quantization.step_m(z) + 1e-7 * z)
    assert np.abs(error).max() < 4e-6  # 3.2 um steps at 90 mm
    np.testing.assert_array_equal(decode_compressed(message.format, message.data)[0][finite],
                                  decoded[finite])

    # the format is read at every publish: jpeg from the next burst on
    set_params("recon", {"normal_map.compressed.format": "jpeg"})
    key = burst_out(set(packed[topics.NORMAL_MAP]))
    message = packed[topics.NORMAL_MAP][key]
    assert message.format == "rgb8; jpeg compressed bgr8"
    assert bytes(message.data[:2]) == b"\xff\xd8"
    jpeg = cv2.cvtColor(cv2.imdecode(np.frombuffer(bytes(message.data), np.uint8),
                                     cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    rgb = image_to_array(raw[topics.NORMAL_MAP][key])
    assert np.abs(jpeg.astype(int) - rgb.astype(int)).mean() < 6.0  # measured 3.6 (ridges)
    assert "Traceback" not in recon.output and " not published: " not in recon.output


@pytest.mark.parametrize(("value", "words"), [
    ("normal_map.enable_pub_plugins:=[image_transport/raw, image_transport/theora]",
     ["normal_map.enable_pub_plugins", "'image_transport/theora'",
      "allowed values: image_transport/raw, image_transport/compressed"]),
    ("depth.enable_pub_plugins:=[image_transport/raw, image_transport/compressed]",
     ["depth.enable_pub_plugins", "use image_transport/compressedDepth",
      "allowed values: image_transport/raw, image_transport/compressedDepth"]),
    ("fingerprint.enable_pub_plugins:=image_transport/compressed",
     ["fingerprint.enable_pub_plugins", "must be a list of transports"]),
    ("normal_map.compressed.format:=tiff", ["must be one of png, jpeg"]),
])
def test_a_bad_transport_setting_stops_recon_at_start(start_node, value: str,
                                                      words: list[str]) -> None:
    recon = start_node("fingerps_recon", "recon_node", "--ros-args", "-p", value)
    assert recon.wait(timeout=30.0) == 2, recon.output
    lines = [line for line in recon.output.splitlines() if "error" in line]
    assert len(lines) == 1 and lines[0].startswith("[recon_node] error: "), recon.output
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert "Traceback" not in recon.output


def test_a_companion_is_encoded_only_while_subscribed_and_never_raises(
        ros_node: Node, monkeypatch: pytest.MonkeyPatch) -> None:
    node = rclpy.create_node("companion_test", namespace=NS, context=ros_node.context)
    executor = SingleThreadedExecutor(context=ros_node.context)
    executor.add_node(node)
    executor.add_node(ros_node)
    try:
        encoded = []
        real = compressed_topics.encode_compressed
        monkeypatch.setattr(compressed_topics, "encode_compressed",
                            lambda *a, **k: encoded.append(1) or real(*a, **k))
        companion = CompressedTopics(node, "picture", qos.OUTPUT_QOS, ParameterChecks(node))
        assert companion.enabled and companion.topic == "picture/compressed"
        assert companion.transports == (compressed_topics.RAW, compressed_topics.COMPRESSED)
        off = CompressedTopics(node, "other", qos.OUTPUT_QOS, ParameterChecks(node),
                               enabled_by_default=False)
        assert not off.enabled and node.has_parameter("other.compressed.png_level")
        image = np.arange(12 * 10, dtype=np.uint8).reshape(12, 10)
        header = Header(frame_id="f")
        header.stamp.sec = 7
        companion.publish(image, "mono8", header)
        off.publish(image, "mono8", header)
        assert encoded == [] and companion.published == 0  # nobody subscribed: no work

        received: list[CompressedImage] = []
        ros_node.create_subscription(CompressedImage, f"{NS}/picture/compressed",
                                     received.append, qos.OUTPUT_QOS)
        assert poll_until(lambda: executor.spin_once(timeout_sec=0.05)
                          or node.count_subscribers(f"{NS}/picture/compressed") >= 1, 20.0), \
            "the subscription never matched"
        companion.publish(image, "mono8", header)
        assert poll_until(lambda: executor.spin_once(timeout_sec=0.05) or received, 20.0), \
            "the compressed image never arrived"
        assert encoded == [1] and companion.published == 1
        back, encoding = decode_compressed(received[0].format, received[0].data)
        assert encoding == "mono8" and received[0].header.stamp.sec == 7
        np.testing.assert_array_equal(back, image)

        # an image it cannot encode: counted, remembered, not raised
        companion.publish(np.zeros((4, 4), np.float32), "32FC1", header)
        companion.publish(np.zeros((4, 4), np.float32), "32FC1", header)
        assert companion.failures == 2 and companion.published == 1
        assert "picture/compressed not published" in companion.last_problem
        assert "'32FC1'" in companion.last_problem
    finally:
        executor.remove_node(ros_node)
        executor.shutdown()
        node.destroy_node()


# ------------------------------------------------------------------ driver: image_raw
IMAGE_RAW_ON = ("image_raw.enable_pub_plugins:="
                "[image_transport/raw, image_transport/compressed]")


@pytest.mark.parametrize(("bit_depth", "encoding"), [(8, "mono8"), (12, "mono16")])
def test_driver_image_raw_companion_is_exact(ros_node: Node, start_node, spin_until,
                                             call_service, bit_depth: int,
                                             encoding: str) -> None:
    """Needs driver_node wired with CompressedTopics for image_raw."""
    raw: dict[tuple[int, int], Image] = {}
    packed: dict[tuple[int, int], CompressedImage] = {}
    # best effort as the publishers (sensor data), deep enough to hold a burst's 7 frames
    profile = QoSProfile(depth=20, reliability=ReliabilityPolicy.BEST_EFFORT)
    _store(ros_node, Image, f"{NS}/{topics.IMAGE_RAW}", profile, raw)
    compressed_sub = _store(ros_node, CompressedImage, f"{NS}/{topics.IMAGE_RAW}/compressed",
                            profile, packed)
    driver = start_node("fingerps_driver", "driver_node", "--ros-args",
                        "-p", f"sim.bit_depth:={bit_depth}", "-p", IMAGE_RAW_ON)
    driver.wait_in_graph(ros_node, "driver", NS)
    spin_until(lambda: compressed_sub.get_publisher_count() >= 1,
               "the driver's image_raw/compressed publisher")
    _capture(ros_node, call_service)

    def matched() -> list[tuple[int, int]]:
        return sorted(set(raw) & set(packed))
    # best effort: wait up to 10 s for the burst's 7 frames, accept what arrived by then
    poll_until(lambda: spin_until(lambda: True, "a spin") or len(matched()) >= 7, 10.0)
    assert matched(), f"no image_raw/compressed with a raw image of its stamp: {driver.output}"
    for key in matched():
        message = packed[key]
        assert message.format == f"{encoding}; png compressed "
        decoded = _png(message)
        assert decoded.dtype == (np.uint16 if encoding == "mono16" else np.uint8)
        np.testing.assert_array_equal(decoded, image_to_array(raw[key]))
    assert "Traceback" not in driver.output


def test_driver_image_raw_companion_is_off_by_default(ros_node: Node, start_node,
                                                      spin_until) -> None:
    driver = start_node("fingerps_driver", "driver_node")
    driver.wait_in_graph(ros_node, "driver", NS)
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.IMAGE_RAW}") >= 1,
               "the driver's image_raw publisher")
    assert ros_node.count_publishers(f"{NS}/{topics.IMAGE_RAW}/compressed") == 0
