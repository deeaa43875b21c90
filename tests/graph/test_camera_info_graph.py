"""The standard camera-calibration path against a real driver_node over DDS: what
``camera_calibration``'s cameracalibrator does on "commit" (sensor_msgs/SetCameraInfo on
``<camera>/set_camera_info``), the driver storing it where its ``camera_info_url`` points and
publishing it at once, and a restarted driver finding it loaded."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from sensor_msgs.srv import SetCameraInfo

from fingerps_calib.intrinsics.camera_info_conversion import intrinsics_to_camera_info
from fingerps_calib.intrinsics.camera_info_url import store_camera_info
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, load_camera_info
from fingerps_driver.simulation import RigConfig, SimulatedRig
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import qos, topics

NS = "/" + topics.NAMESPACE
SERVICE = f"{NS}/driver/set_camera_info"  # camera_info_manager's ~/set_camera_info


def _burst_info(ros_node: Node, call_service) -> CameraInfo:
    client = ros_node.create_client(CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}")
    response = call_service(client, CaptureBurst.Request())
    ros_node.destroy_client(client)
    assert response.success, response.message
    return response.burst.camera_info


def _calibration(width: int, height: int, fx: float) -> CameraInfo:
    """What cameracalibrator sends: K, D (plumb_bob), R, P of its fit."""
    k = np.array([[fx, 0.0, width / 2 - 0.5], [0.0, fx * 1.001, height / 2 + 0.5],
                  [0.0, 0.0, 1.0]])
    intrinsics = CameraIntrinsics(width, height, k, "plumb_bob",
                                  np.array([-0.02, 0.01, 1e-4, -2e-4, 0.0]), "any")
    return intrinsics_to_camera_info(intrinsics, width=width, height=height)


def test_set_camera_info_is_stored_published_at_once_and_loaded_after_a_restart(
        ros_node: Node, start_node, spin_until, call_service) -> None:
    rig = SimulatedRig(RigConfig())
    width, height = rig.camera.width, rig.camera.height
    store = Path(os.environ["ROS_HOME"]) / "camera_info" / "fingerps_sim.yaml"
    driver = start_node("fingerps_driver", "driver_node")
    driver.wait_in_graph(ros_node, "driver", NS)
    # No calibration yet: the default URL is looked at, the sim rig's truth published.
    assert not store.exists()
    before = _burst_info(ros_node, call_service)
    np.testing.assert_allclose(np.reshape(before.k, (3, 3)), rig.camera_matrix)
    assert f"no camera calibration at {store}" in driver.output

    infos: list[CameraInfo] = []
    ros_node.create_subscription(CameraInfo, f"{NS}/{topics.CAMERA_INFO}", infos.append,
                                 qos.SENSOR_QOS)
    client = ros_node.create_client(SetCameraInfo, SERVICE)
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.CAMERA_INFO}") >= 1,
               "the driver's camera_info publisher")

    # Refused: the wrong size, a K that is not finite, an unknown distortion model.
    wrong_size = _calibration(width + 2, height, 900.0)
    not_finite = _calibration(width, height, 900.0)
    not_finite.k[4] = float("nan")
    unknown_model = _calibration(width, height, 900.0)
    unknown_model.distortion_model = "kannala_brandt_x"
    for bad, reason in ((wrong_size, f"the camera delivers {width}x{height}"),
                        (not_finite, "non-finite"), (unknown_model, "is not one of")):
        response = call_service(client, SetCameraInfo.Request(camera_info=bad))
        assert not response.success and reason in response.status_message, \
            response.status_message
    assert not store.exists()

    # Accepted: stored owner-only at the URL's file, and a CameraInfo published at once.
    sent = _calibration(width, height, 1234.5)
    response = call_service(client, SetCameraInfo.Request(camera_info=sent))
    assert response.success, response.status_message
    assert response.status_message == f"stored in {store}"
    assert stat.S_IMODE(store.stat().st_mode) == 0o600
    saved = load_camera_info(store)
    assert saved.camera_name == "fingerps_sim" and saved.fx == 1234.5
    spin_until(lambda: any(i.k[0] == 1234.5 for i in infos),
               "the new CameraInfo, published without a burst", timeout=10.0)
    published = next(i for i in infos if i.k[0] == 1234.5)
    assert list(published.d) == list(sent.d) and list(published.p) == list(sent.p)
    assert published.header.frame_id == "fingerps_camera_optical_frame"
    assert list(_burst_info(ros_node, call_service).k) == list(sent.k)

    # A restarted driver loads it from the same URL.
    driver.stop()
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.CAMERA_INFO}") == 0,
               "the driver gone")
    again = start_node("fingerps_driver", "driver_node")
    again.wait_in_graph(ros_node, "driver", NS)
    after = _burst_info(ros_node, call_service)
    assert list(after.k) == list(sent.k) and list(after.d) == list(sent.d)
    assert after.distortion_model == "plumb_bob"
    assert f"camera calibration: {store}" in again.output


def test_an_explicit_url_that_is_missing_or_of_another_size_says_what_to_run(
        ros_node: Node, start_node, spin_until, call_service, tmp_path: Path) -> None:
    url = f"file://{tmp_path}/cal/${{NAME}}.yaml"
    driver = start_node("fingerps_driver", "driver_node", "--ros-args",
                        "-p", f"camera_info_url:={url}", "-p", "camera_name:=kiosk_cam")
    driver.wait_in_graph(ros_node, "driver", NS)
    _burst_info(ros_node, call_service)  # it runs: set_camera_info can still calibrate it
    lines = [line for line in driver.output.splitlines()
             if f"no camera calibration at {tmp_path}/cal/kiosk_cam.yaml" in line]
    assert len(lines) == 1, driver.output
    assert "WARN" in lines[0] and "cameracalibrator" in lines[0]
    assert f"camera/set_camera_info:={SERVICE}" in lines[0]
    assert f"image:={NS}/image_raw" in lines[0]
    # set_camera_info makes the folder and the file the URL names
    rig = SimulatedRig(RigConfig())
    client = ros_node.create_client(SetCameraInfo, SERVICE)
    response = call_service(client, SetCameraInfo.Request(
        camera_info=_calibration(rig.camera.width, rig.camera.height, 800.0)))
    assert response.success and (tmp_path / "cal" / "kiosk_cam.yaml").exists()
    driver.stop()

    # A file of another size: one line naming both sizes, the driver still runs.
    small = CameraIntrinsics(320, 240, np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]]),
                             "plumb_bob", np.zeros(5), "kiosk_cam")
    store_camera_info(tmp_path / "cal" / "kiosk_cam.yaml", small)
    again = start_node("fingerps_driver", "driver_node", "--ros-args",
                       "-p", f"camera_info_url:={url}", "-p", "camera_name:=kiosk_cam")
    again.wait_in_graph(ros_node, "driver", NS)
    info = _burst_info(ros_node, call_service)
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), rig.camera_matrix)
    lines = [line for line in again.output.splitlines() if "is for 320x240 images" in line]
    assert len(lines) == 1 and (f"delivers {rig.camera.width}x{rig.camera.height}"
                                in lines[0]), again.output
