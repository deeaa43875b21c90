"""recon_node as a real process, alone: the test plays the driver and the calibration.

The test publishes a LightCalibration made from the simulated rig's truth (distant-light
directions from the apex, optical frame; relative intensities at the apex) and Burst
messages it renders itself. The node must publish the outputs of each complete burst with
the burst's header; refuse, without outputs, a burst that lacks an LED's frame (counted as
``bursts_incomplete``), a burst with nothing in view and a burst of colour images
(``bursts_failed``); keep running
and reconstruct the next good burst; and stop cleanly on SIGINT.

Bound on the normals' mean angular error: 3.5 deg, as in tests/core/test_pipeline.py (the
same data through the same pipeline measures 3.21 deg; through the node the relative
intensities are scaled to a maximum of 1, which leaves the directions unchanged).
"""

from __future__ import annotations

import signal
from collections import defaultdict

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header

from fingerps_driver.simulation import FingerTruth, Scene, SimulatedRig
from fingerps_msgs.msg import Burst, LightCalibration, TaggedFrame
from fingerps_recon import qos, topics
from fingerps_recon.angular_error import angular_error_deg
from fingerps_recon.frames import optical_to_ps, ps_to_optical
from fingerps_recon.image_conversion import array_to_image, image_to_array
from fingerps_recon.point_cloud_conversion import cloud_to_points

NS = "/" + topics.NAMESPACE
FRAME_ID = "fingerps_camera_optical_frame"
MAX_MEAN_ERROR_DEG = 3.5
OUTPUTS = {topics.NORMALS: Image, topics.NORMAL_MAP: Image, topics.DEPTH: Image,
           topics.ALBEDO: Image, topics.POINTS: PointCloud2}


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig()


@pytest.fixture(scope="module")
def images(rig: SimulatedRig) -> np.ndarray:
    return np.stack([rig.render(Scene.FINGER, [k], rng=np.random.default_rng(30 + k))
                     for k in range(rig.led_count)])


@pytest.fixture(scope="module")
def truth(rig: SimulatedRig) -> FingerTruth:
    return rig.finger_truth()


def _calibration(rig: SimulatedRig) -> LightCalibration:
    directions = ps_to_optical(rig.light_directions_ps())
    intensities = rig.light_intensities()
    return LightCalibration(
        header=Header(frame_id=FRAME_ID), camera_name="graph_test",
        directions=[Vector3(x=float(x), y=float(y), z=float(z)) for x, y, z in directions],
        relative_intensities=[float(i) for i in intensities / intensities.max()],
        sphere_radius=rig.config.sphere_radius_m)


@pytest.fixture(scope="module")
def empty_images(rig: SimulatedRig) -> np.ndarray:
    return np.stack([rig.render(Scene.EMPTY, [k], rng=np.random.default_rng(40 + k))
                     for k in range(rig.led_count)])


def _burst(rig: SimulatedRig, images: np.ndarray, burst_id: int,
           leds: list[int] | None = None, encoding: str = "mono8") -> Burst:
    header = Header(stamp=Time(sec=1000 + burst_id, nanosec=burst_id), frame_id=FRAME_ID)
    count = len(images)
    frames = [TaggedFrame(header=header, burst_id=burst_id, led_index=k, led_count=count,
                          exposure_time=0.01, led_intensity=1.0,
                          image=array_to_image(images[k], encoding=encoding, header=header))
              for k in (range(count) if leds is None else leds)]
    info = CameraInfo(header=header, width=rig.config.width, height=rig.config.height,
                      k=[float(x) for x in rig.camera_matrix.reshape(-1)])
    return Burst(header=header, burst_id=burst_id, frames=frames, camera_info=info)


def _key(header: Header) -> tuple[int, int]:
    return header.stamp.sec, header.stamp.nanosec


def _diagnostic_values(arrays: list[DiagnosticArray]) -> list[dict[str, str]]:
    return [{kv.key: kv.value for kv in status.values}
            for array in arrays for status in array.status
            if status.name.startswith("recon")]


def test_recon_node_reconstructs_complete_bursts_and_survives_broken_ones(
        ros_node: Node, start_node, spin_until, rig: SimulatedRig, images: np.ndarray,
        empty_images: np.ndarray, truth: FingerTruth) -> None:
    # The calibration is published before recon starts: transient-local brings it.
    lights_pub = ros_node.create_publisher(
        LightCalibration, f"{NS}/{topics.LIGHT_CALIBRATION}", qos.CALIBRATION_QOS)
    lights_pub.publish(_calibration(rig))
    burst_pub = ros_node.create_publisher(Burst, f"{NS}/{topics.BURST}", qos.BURST_QOS)
    received: dict[str, dict[tuple[int, int], object]] = defaultdict(dict)
    subscriptions = []
    for name, msg_type in OUTPUTS.items():
        def store(msg, name=name) -> None:
            received[name][_key(msg.header)] = msg
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

    incomplete = _burst(rig, images, 1, leds=[0, 1, 2, 4, 5, 6])
    nothing_in_view = _burst(rig, empty_images, 2)
    colour = _burst(rig, np.repeat(images[..., None], 3, axis=-1), 5, encoding="rgb8")
    good = _burst(rig, images, 3)
    for burst in (incomplete, nothing_in_view, colour, good):  # queue_depth 4: none dropped
        burst_pub.publish(burst)
    # One worker, in order: once the good burst's outputs are out, the others are done.
    spin_until(lambda: all(_key(good.header) in received[name] for name in OUTPUTS),
               "the outputs of the complete burst", timeout=20.0)
    assert all(set(received[name]) == {_key(good.header)} for name in OUTPUTS), \
        {name: set(r) for name, r in received.items()}
    assert recon.running()

    height, width = rig.config.height, rig.config.width
    normals_msg = received[topics.NORMALS][_key(good.header)]
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

    normal_map = received[topics.NORMAL_MAP][_key(good.header)]
    assert normal_map.encoding == "rgb8"
    rgb = image_to_array(normal_map)
    assert rgb.shape == (height, width, 3) and np.all(rgb[~mask] == 0) and rgb[mask].any()

    depth_msg = received[topics.DEPTH][_key(good.header)]
    assert depth_msg.encoding == "32FC1" and depth_msg.header.frame_id == FRAME_ID
    depth = image_to_array(depth_msg)
    np.testing.assert_array_equal(np.isfinite(depth), mask)
    assert np.all((depth[mask] > 0.085) & (depth[mask] < 0.100))

    albedo_msg = received[topics.ALBEDO][_key(good.header)]
    assert albedo_msg.encoding == "32FC1"
    albedo = image_to_array(albedo_msg)
    assert np.all(albedo[mask] > 0) and np.all(albedo[~mask] == 0)

    cloud = received[topics.POINTS][_key(good.header)]
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
    again = _burst(rig, images, 4)
    burst_pub.publish(again)
    spin_until(lambda: all(_key(again.header) in received[name] for name in OUTPUTS),
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
