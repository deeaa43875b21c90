"""recon_node as a real process, alone: the test plays the driver and the calibration.

The test publishes a LightCalibration made from the simulated rig's truth (distant-light
directions from the apex, optical frame; relative intensities at the apex) and Burst
messages it renders itself. The node must publish the outputs of each complete burst with
the burst's header; refuse, without outputs, a burst that lacks an LED's frame (counted as
``bursts_incomplete``), a burst with nothing in view and a burst of colour images
(``bursts_failed``); keep running
and reconstruct the next good burst; and stop cleanly on SIGINT.

Every malformed input: bursts of 0x0 or 0-wide images, beyond the size bounds,
with too many frames, step and data that disagree, duplicate or unknown LED indices, float
images with NaN, a NaN dark frame; degenerate light calibrations (a zero direction,
parallel directions, NaN intensities with LED positions), NaN flat-field maps, flat maps of
another size. recon_node must keep running, count each, go WARN/ERROR and back to OK once
good bursts flow, reconstruct the good bursts, and print no traceback.

Bound on the normals' mean angular error: 3.5 deg, as in tests/core/test_pipeline.py (the
same data through the same pipeline measures 3.21 deg; through the node the relative
intensities are scaled to a maximum of 1, which leaves the directions unchanged).
"""

from __future__ import annotations

import signal
from collections import defaultdict

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, Vector3
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2
from stamps import stamp_key
from std_msgs.msg import Header

from fingerps_driver.simulation import FingerTruth, Scene, SimulatedRig
from fingerps_msgs.msg import Burst, FlatField, LightCalibration, TaggedFrame
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import array_to_image, image_to_array
from fingerps_ros.point_cloud_conversion import cloud_to_points

NS = "/" + topics.NAMESPACE
FRAME_ID = "fingerps_camera_optical_frame"
MAX_MEAN_ERROR_DEG = 3.5
OUTPUTS = {topics.NORMALS: Image, topics.NORMAL_MAP: Image, topics.DEPTH: Image,
           topics.ALBEDO: Image, topics.POINTS: PointCloud2}


@pytest.fixture(scope="module")
def truth(rig: SimulatedRig) -> FingerTruth:
    return rig.finger_truth()


@pytest.fixture(scope="module")
def empty_images(rig: SimulatedRig) -> np.ndarray:
    return rig.render_burst(Scene.EMPTY, seed=40)


def _diagnostic_values(arrays: list[DiagnosticArray]) -> list[dict[str, str]]:
    return [{kv.key: kv.value for kv in status.values}
            for array in arrays for status in array.status
            if status.name.startswith("recon")]


def test_recon_node_reconstructs_complete_bursts_and_survives_broken_ones(
        ros_node: Node, start_node, spin_until, rig: SimulatedRig, rig_messages,
        finger_images: np.ndarray, empty_images: np.ndarray, truth: FingerTruth) -> None:
    # The calibration is published before recon starts: transient-local brings it.
    lights_pub = ros_node.create_publisher(
        LightCalibration, f"{NS}/{topics.LIGHT_CALIBRATION}", qos.CALIBRATION_QOS)
    lights_pub.publish(rig_messages.light_calibration("graph_test"))
    burst_pub = ros_node.create_publisher(Burst, f"{NS}/{topics.BURST}", qos.BURST_QOS)
    received: dict[str, dict[tuple[int, int], object]] = defaultdict(dict)
    subscriptions = []
    for name, msg_type in OUTPUTS.items():
        def store(msg, name=name) -> None:
            received[name][stamp_key(msg.header)] = msg
        subscriptions.append(ros_node.create_subscription(
            msg_type, f"{NS}/{name}", store, qos.OUTPUT_QOS))
    diagnostics: list[DiagnosticArray] = []
    ros_node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diagnostics.append, 10)

    recon = start_node("fingerps_recon", "recon_node", "--ros-args", "-p", "queue_depth:=4")
    recon.wait_in_graph(ros_node, "recon", NS)
    spin_until(lambda: burst_pub.get_subscription_count() >= 1
               and all(s.get_publisher_count() >= 1 for s in subscriptions),
               "recon's burst subscription and output publishers")
    spin_until(lambda: any(v.get("calibrated") == "True"
                           for v in _diagnostic_values(diagnostics)),
               "recon to report the light calibration received")
    spin_until(lambda: any(v.get("ready") == "True" for v in _diagnostic_values(diagnostics)),
               "recon to report its kernels warmed up (ready)")
    assert "reconstruction ready: " in recon.output  # one log line: compiled or loaded

    incomplete = rig_messages.burst(finger_images, 1, leds=[0, 1, 2, 4, 5, 6])
    nothing_in_view = rig_messages.burst(empty_images, 2)
    colour = rig_messages.burst(np.repeat(finger_images[..., None], 3, axis=-1), 5, encoding="rgb8")
    good = rig_messages.burst(finger_images, 3)
    for burst in (incomplete, nothing_in_view, colour, good):  # queue_depth 4: none dropped
        burst_pub.publish(burst)
    # One worker, in order: once the good burst's outputs are out, the others are done.
    spin_until(lambda: all(stamp_key(good.header) in received[name] for name in OUTPUTS),
               "the outputs of the complete burst", timeout=20.0)
    assert all(set(received[name]) == {stamp_key(good.header)} for name in OUTPUTS), \
        {name: set(r) for name, r in received.items()}
    assert recon.running()

    height, width = rig.camera.height, rig.camera.width
    normals_msg = received[topics.NORMALS][stamp_key(good.header)]
    assert normals_msg.encoding == "32FC3" and normals_msg.header.frame_id == FRAME_ID
    normals_optical = image_to_array(normals_msg)
    assert normals_optical.shape == (height, width, 3)
    norms = np.linalg.norm(normals_optical, axis=-1)
    mask = norms > 0
    assert (mask & truth.mask).sum() > 0.9 * truth.mask.sum()
    np.testing.assert_allclose(norms[mask], 1.0, atol=1e-5)
    assert np.all(normals_optical[mask][:, 2] < 0)  # optical frame: facing the camera
    errors = angular_error_deg(optical_to_ps(normals_optical), truth.normals_ps,
                               mask=mask & truth.mask)
    mean_error = float(np.nanmean(errors))
    print(f"\nnormals' mean angular error through recon_node {mean_error:.3f} deg")
    assert mean_error < MAX_MEAN_ERROR_DEG

    normal_map = received[topics.NORMAL_MAP][stamp_key(good.header)]
    assert normal_map.encoding == "rgb8"
    rgb = image_to_array(normal_map)
    assert rgb.shape == (height, width, 3) and np.all(rgb[~mask] == 0) and rgb[mask].any()
    # Watched, the normal map shows the ridge-enhanced normals (Eq. 12; recon_node skips the
    # enhancement only while nobody subscribes to it), not the plain ones.
    normals_ps = optical_to_ps(normals_optical)
    enhanced_rgb = normal_map_rgb(enhance_ridges(normals_ps, mask=mask), mask=mask)
    plain_rgb = normal_map_rgb(normals_ps, mask=mask)
    off_enhanced = np.abs(rgb.astype(int) - enhanced_rgb)[mask].max()
    off_plain = np.abs(rgb.astype(int) - plain_rgb)[mask].mean()
    assert off_enhanced <= 1 and off_plain > 1.0, (off_enhanced, off_plain)

    depth_msg = received[topics.DEPTH][stamp_key(good.header)]
    assert depth_msg.encoding == "32FC1" and depth_msg.header.frame_id == FRAME_ID
    depth = image_to_array(depth_msg)
    np.testing.assert_array_equal(np.isfinite(depth), mask)
    assert np.all((depth[mask] > 0.085) & (depth[mask] < 0.100))

    albedo_msg = received[topics.ALBEDO][stamp_key(good.header)]
    assert albedo_msg.encoding == "32FC1"
    albedo = image_to_array(albedo_msg)
    assert np.all(albedo[mask] > 0) and np.all(albedo[~mask] == 0)

    cloud = received[topics.POINTS][stamp_key(good.header)]
    assert cloud.header.frame_id == FRAME_ID
    points, intensity = cloud_to_points(cloud)
    assert points.shape == (int(mask.sum()), 3) and intensity.shape == (points.shape[0],)
    np.testing.assert_allclose(np.sort(points[:, 2]), np.sort(depth[mask]), rtol=1e-6)

    def counted() -> bool:
        return any(int(v.get("bursts_incomplete", 0)) >= 1
                   and int(v.get("bursts_failed", 0)) >= 2
                   and int(v.get("bursts_done", 0)) >= 1
                   and v.get("bursts_dropped") == "0"
                   for v in _diagnostic_values(diagnostics))
    spin_until(counted, "diagnostics counting the incomplete, the failed and the done burst",
               timeout=5.0)
    assert counted(), _diagnostic_values(diagnostics)[-1]

    # A second burst of the same camera with the same calibration: nothing is prepared again.
    again = rig_messages.burst(finger_images, 4)
    burst_pub.publish(again)
    spin_until(lambda: all(stamp_key(again.header) in received[name] for name in OUTPUTS),
               "the outputs of the second complete burst", timeout=20.0)
    spin_until(lambda: any(int(v.get("bursts_done", 0)) >= 2 for v in
                           _diagnostic_values(diagnostics)),
               "diagnostics counting the second burst", timeout=5.0)
    last = [v for v in _diagnostic_values(diagnostics) if int(v.get("bursts_done", 0)) >= 2]
    assert last[-1]["calibrations_prepared"] == "1", last[-1]
    # Where the time went (medians over the recent bursts, ms): all stages reported.
    assert 0 < float(last[-1]["reconstruction_ms"]) < float(last[-1]["capture_to_published_ms"])
    assert float(last[-1]["publish_ms"]) > 0 and float(last[-1]["queue_wait_ms"]) >= 0

    recon.send_signal(signal.SIGINT)
    assert recon.wait() == 0, recon.output
    assert "Traceback" not in recon.output
    assert "missing [3]" in recon.output  # the refusal was logged with its reason


def _status(arrays: list[DiagnosticArray]) -> tuple[int, dict[str, str]] | None:
    """The level and values of recon's latest status, or None before the first."""
    found = [status for array in arrays for status in array.status
             if status.name.startswith("recon")]
    if not found:
        return None
    last = found[-1]
    return int.from_bytes(last.level, "little"), {kv.key: kv.value for kv in last.values}


def _flat(maps: np.ndarray) -> FlatField:
    return FlatField(header=Header(frame_id=FRAME_ID), camera_name="graph_test",
                     maps=[array_to_image(m, encoding="32FC1") for m in maps],
                     relative_intensities=[1.0] * len(maps))


def _malformed_bursts(messages, images: np.ndarray) -> dict[str, tuple[str, Burst]]:
    """name -> (the counter that must count it, the burst of ``messages``, the fixture
    ``rig_messages``); burst ids from 100."""
    count = messages.rig.led_count
    made: dict[str, tuple[str, Burst]] = {}

    def add(name: str, counter: str, burst: Burst) -> None:
        made[name] = (counter, burst)

    add("0x0 images", "bursts_rejected",
        messages.burst(np.zeros((count, 0, 0), np.uint8), 100))
    add("0-wide images", "bursts_rejected",
        messages.burst(np.zeros((count, 16, 0), np.uint8), 101))
    add("images wider than max_image_width", "bursts_rejected",
        messages.burst(np.full((count, 1, 4097), 200, np.uint8), 102))
    huge = messages.burst(images, 103)
    for frame in huge.frames:  # a header claiming 7 x 100000^2 px over a few bytes
        frame.image = Image(height=100_000, width=100_000, encoding="mono8", step=100_000,
                            data=bytes(64))
    add("a 100000x100000 header over 64 bytes", "bursts_rejected", huge)
    add("more frames than max_burst_frames", "bursts_rejected",
        messages.burst(np.concatenate([images] * 3), 104))
    short = messages.burst(images, 105)
    short.frames[2].image.data = bytes(short.frames[2].image.data)[:-10]
    add("data shorter than step x height", "bursts_failed", short)
    stepped = messages.burst(images, 106)
    stepped.frames[4].image.step = stepped.frames[4].image.width - 3
    add("step shorter than a row", "bursts_failed", stepped)
    floats = images.astype(np.float32)
    floats[:, 5, 5], floats[:, 6, 6] = np.nan, np.inf
    add("float images with NaN and inf", "bursts_failed",
        messages.burst(floats, 107, encoding="32FC1"))
    nan_dark = messages.burst(images, 108)
    dark = np.full(images.shape[1:], np.nan, np.float32)
    nan_dark.has_dark_frame = True
    nan_dark.dark_frame = TaggedFrame(header=nan_dark.header, burst_id=108,
                                      image=array_to_image(dark, encoding="32FC1"))
    add("a NaN 32FC1 dark frame", "bursts_failed", nan_dark)
    add("duplicate LED indices", "bursts_incomplete",
        messages.burst(images, 109, leds=[0, 1, 2, 3, 4, 5, 5]))
    unknown = messages.burst(images, 110)
    unknown.frames[6].led_index = 77
    add("an unknown LED index", "bursts_incomplete", unknown)
    return made


def test_recon_node_survives_every_malformed_input(
        ros_node: Node, start_node, spin_until, rig: SimulatedRig, rig_messages,
        finger_images: np.ndarray) -> None:
    lights_pub = ros_node.create_publisher(
        LightCalibration, f"{NS}/{topics.LIGHT_CALIBRATION}", qos.CALIBRATION_QOS)
    flat_pub = ros_node.create_publisher(FlatField, f"{NS}/{topics.FLAT_FIELD}",
                                         qos.CALIBRATION_QOS)
    good_lights = rig_messages.light_calibration("graph_test")
    lights_pub.publish(good_lights)
    burst_pub = ros_node.create_publisher(Burst, f"{NS}/{topics.BURST}", qos.BURST_QOS)
    received: dict[tuple[int, int], int] = defaultdict(int)  # outputs per burst stamp
    subscriptions = []
    for name, msg_type in OUTPUTS.items():
        def store(msg, name=name) -> None:
            received[stamp_key(msg.header)] += 1
        subscriptions.append(ros_node.create_subscription(
            msg_type, f"{NS}/{name}", store, qos.OUTPUT_QOS))
    diagnostics: list[DiagnosticArray] = []
    ros_node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diagnostics.append, 10)

    def level_and(check) -> bool:
        status = _status(diagnostics)
        return status is not None and check(*status)

    def until_status(check, what: str, timeout: float) -> None:
        try:
            spin_until(lambda: level_and(check), what, timeout=timeout)
        except pytest.fail.Exception:
            pytest.fail(f"waiting for {what}; last status {_status(diagnostics)}; recon's "
                        f"output:\n{recon.output[-4000:]}")

    recon = start_node("fingerps_recon", "recon_node", "--ros-args", "-p", "queue_depth:=16",
                       "-p", "health_window:=3")
    recon.wait_in_graph(ros_node, "recon", NS)
    spin_until(lambda: burst_pub.get_subscription_count() >= 1
               and flat_pub.get_subscription_count() >= 1
               and all(s.get_publisher_count() >= 1 for s in subscriptions),
               "recon's subscriptions and output publishers")
    until_status(lambda level, v: v["ready"] == v["calibrated"] == "True" and level == 0,
                 "recon ready, calibrated and OK", timeout=30.0)

    # 1. Malformed bursts: each counted, none reconstructed, ERROR (the last 3 all failed).
    expected: dict[str, int] = defaultdict(int)
    for name, (counter, burst) in _malformed_bursts(rig_messages, finger_images).items():
        burst_pub.publish(burst)  # one at a time (the burst topic keeps 4): each counted
        expected[counter] += 1

        def counted(level: int, values: dict[str, str]) -> bool:
            return all(int(values[c]) == n for c, n in expected.items())
        until_status(counted, f"recon counting {name} in {counter} ({dict(expected)})",
                     timeout=10.0)
    until_status(lambda level, v: level == 2,
                 "diagnostics level ERROR after the malformed bursts", timeout=5.0)
    _, values = _status(diagnostics)
    assert values["bursts_done"] == "0" and values["bursts_dropped"] == "0", values
    assert values["unexpected_errors"] == "0", values
    assert not received, received
    assert recon.running(), recon.output

    # 2. Degenerate calibrations: each refused on arrival (the good one stays in force).
    lights = rig.light_directions_ps()
    zero = lights.copy()
    zero[3] = 0.0
    nan_with_leds = rig_messages.light_calibration("graph_test")
    nan_with_leds.relative_intensities = [float("nan")] * rig.led_count
    nan_with_leds.led_positions = [Point(x=float(x), y=float(y), z=float(z))
                                   for x, y, z in rig.led_positions_optical]
    parallel = rig_messages.light_calibration("graph_test")
    parallel.directions = [parallel.directions[0]] * rig.led_count
    zero_msg = rig_messages.light_calibration("graph_test")
    zero_msg.directions = [Vector3(x=float(x), y=float(y), z=float(z))
                           for x, y, z in ps_to_optical(zero)]
    nan_maps = np.ones(finger_images.shape, np.float32)
    nan_maps[:, 100:200, 100:200] = np.nan
    refusals = [(lights_pub, zero_msg), (lights_pub, parallel), (lights_pub, nan_with_leds),
                (flat_pub, _flat(nan_maps))]
    for n, (publisher, msg) in enumerate(refusals, start=1):
        publisher.publish(msg)  # one at a time: the calibration topics keep the last only
        until_status(lambda level, v, n=n: int(v["calibrations_refused"]) == n,
                     f"recon refusing degenerate calibration {n}", timeout=10.0)
    # Flat maps of another size: taken, but a burst of the camera's size cannot use them.
    flat_pub.publish(_flat(np.ones((rig.led_count, 20, 30), np.float32)))
    spin_until(lambda: "flat field received: 7 maps (20, 30)" in recon.output,
               "recon taking the small flat field", timeout=10.0)

    # 3. A good burst: reconstructed without the flat field (counted); WARN, not ERROR.
    good = rig_messages.burst(finger_images, 200)
    burst_pub.publish(good)
    spin_until(lambda: received[stamp_key(good.header)] == len(OUTPUTS),
               "the outputs of the good burst after the malformed inputs", timeout=30.0)
    until_status(lambda level, v: level == 1 and v["bursts_done"] == "1"
                 and v["bursts_without_flat_field"] == "1",
                 "diagnostics WARN with the good burst done without the flat field",
                 timeout=5.0)

    # 4. Good calibrations again and good bursts flowing: back to OK.
    lights_pub.publish(good_lights)
    flat_pub.publish(_flat(np.ones(finger_images.shape, np.float32)))
    spin_until(lambda: recon.output.count("flat field received: 7 maps") == 2,
               "recon taking the flat field of the camera's size", timeout=10.0)
    spin_until(lambda: recon.output.count("light calibration received") == 2,
               "recon taking the good light calibration again", timeout=10.0)
    more = [rig_messages.burst(finger_images, 201 + i) for i in range(3)]
    for burst in more:
        burst_pub.publish(burst)
    spin_until(lambda: all(received[stamp_key(b.header)] == len(OUTPUTS) for b in more),
               "the outputs of the good bursts", timeout=30.0)
    until_status(lambda level, v: level == 0 and v["bursts_done"] == "4",
                 "diagnostics back to OK once good bursts flow", timeout=5.0)
    _, values = _status(diagnostics)
    assert values["bursts_without_flat_field"] == "1", values
    assert values["unexpected_errors"] == "0", values
    assert set(received) == {stamp_key(b.header) for b in [good, *more]}, set(received)

    assert recon.running(), recon.output
    recon.send_signal(signal.SIGINT)
    assert recon.wait() == 0, recon.output
    output = recon.output
    assert "Traceback" not in output and "zero-size array" not in output, output
    for needle in ("empty", "beyond max_image_width", "max_burst_frames", "too few",
                   "one grey level", "dark frame", "missing", "light calibration refused",
                   "flat field refused", "not unit", "parallel", "intensities", "not used"):
        assert needle in output, f"{needle!r} not logged:\n{output}"
