"""driver_node with the folder camera and the per-LED parameters, as a real process; bad
start-up input (camera, port, parameters) ends in one clear line and exit code 2."""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from rclpy.node import Node

from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, save_camera_info
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array

NS = "/" + topics.NAMESPACE
H, W = 12, 16


def _folder(path: Path, sizes=None) -> Path:
    """Seven 16-bit images; LED i's pixels are 1000 * (i + 1)."""
    path.mkdir()
    names = []
    for i in range(7):
        height, width = sizes[i] if sizes else (H, W)
        names.append(f"led_{i}.png")
        assert cv2.imwrite(str(path / names[-1]),
                           np.full((height, width), 1000 * (i + 1), np.uint16))
    (path / "filenames.txt").write_text("\n".join(names) + "\n")
    return path


def test_folder_camera_replays_the_led_images_in_the_planned_order(
        ros_node: Node, start_node, spin_until, call_service, set_parameters, driver_topics,
        tmp_path: Path) -> None:
    folder = _folder(tmp_path / "capture")
    info_file = tmp_path / "camera.yaml"
    k = np.array([[500.0, 0, 7.5], [0, 500.0, 5.5], [0, 0, 1]])
    save_camera_info(info_file, CameraIntrinsics(W, H, k, "plumb_bob", np.zeros(5), "bench"))
    exposures = [0.001 * (i + 1) for i in range(7)]
    levels = [0.5, 1.0, 0.25, 1.0, 1.0, 1.0, 0.75]
    driver = start_node(
        "fingerps_driver", "driver_node", "--ros-args", "-p", "camera:=folder",
        "-p", f"camera_folder:={folder}", "-p", f"camera_info_file:={info_file}",
        "-p", "led_order:=[6, 5, 4, 3, 2, 1, 0]",
        "-p", f"exposure_times:={exposures}", "-p", f"led_levels:={levels}")
    driver.wait_in_graph(ros_node, "driver", NS)
    bursts, _, client = driver_topics
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.FRAMES}") >= 1,
               "the driver's publishers")

    response = call_service(client, CaptureBurst.Request(with_dark_frame=True))
    assert response.success, response.message
    burst = response.burst
    assert [f.led_index for f in burst.frames] == list(range(7))  # published in LED order
    for frame in burst.frames:
        image = image_to_array(frame.image)
        assert frame.image.encoding == "mono16" and image.shape == (H, W)
        assert np.all(image == 1000 * (frame.led_index + 1))
        assert frame.exposure_time == pytest.approx(exposures[frame.led_index])
        assert frame.led_intensity == pytest.approx(round(255 * levels[frame.led_index]) / 255)
    stamps = {f.led_index: (f.header.stamp.sec, f.header.stamp.nanosec) for f in burst.frames}
    assert sorted(stamps, key=stamps.get) == [6, 5, 4, 3, 2, 1, 0]  # captured in led_order
    assert not image_to_array(burst.dark_frame.image).any()
    assert list(burst.camera_info.k) == pytest.approx(k.ravel().tolist())
    assert (burst.camera_info.width, burst.camera_info.height) == (W, H)
    spin_until(lambda: bursts, "the burst on its topic")

    # a bad value set at run time is refused with a reason, the good one taken
    def set_order(order):
        return set_parameters("driver", {"led_order": order})[0]

    refused = set_order([0, 0, 1])
    assert not refused.successful and "more than once" in refused.reason
    assert set_order([3, 1]).successful
    response = call_service(client, CaptureBurst.Request())
    assert response.success, response.message
    assert [f.led_index for f in response.burst.frames] == [1, 3]


@pytest.fixture
def run_driver(ros_domain: int, installed) -> Callable[..., subprocess.CompletedProcess]:
    """``run_driver(*ros_args)``: driver_node run to its end in the test's ROS domain."""
    exe = installed("fingerps_driver", "driver_node")

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([exe, "--ros-args", *args], capture_output=True, text=True,
                              timeout=60)
    return run


@pytest.mark.parametrize(("args", "expected"), [
    (["-p", "port:=/dev/fingerps_no_such_port"], "/dev/fingerps_no_such_port"),
    (["-p", "sim.scene:=banana"], "sim.scene"),
    (["-p", "led_count:=99"], "led_count"),
    (["-p", "sim.sceen:=sphere"], "sim.sceen"),
    (["--params-file", "/nonexistent/fingerps.yaml"], "params file"),
    (["-p", "led_order:=[0, 9]"], "led_order"),
    (["-p", "exposure_times:=[0.01, 0.02]"], "2 entries for 7 LEDs"),
    (["-p", "led_levels:=[1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 2.0]"], "levels are in 0..1"),
    (["-p", "led_levels:=[a, b, c, d, e, f, g]"], "must be a list of numbers"),  # dynamic type
    (["-p", "exposure_times:=0.01"], "must be a list of numbers"),
    (["-p", "camera:=gopro"], "camera"),
    (["-p", "camera:=v4l2", "-p", "camera_device:=/dev/fingerps_no_camera"],
     "cannot open camera '/dev/fingerps_no_camera'"),
    (["-p", "camera:=folder"], "camera_folder"),
    (["-p", "camera_pixel_format:=mono16"], "sim.bit_depth"),
    (["-p", "camera_info_file:=/nonexistent/camera.yaml"], "/nonexistent/camera.yaml"),
    (["-p", "camera_info_url:=http://host/c.yaml"], "is not a calibration URL"),
    (["-p", "camera_info_url:=package://fingerps_nowhere/c.yaml"], "is not installed"),
    (["-p", "camera_info_url:=file:///c.yaml", "-p", "camera_info_file:=/c.yaml"],
     "not both"),
    (["-p", "camera_name:=kiosk-cam"], "letters, digits and '_'"),
])
def test_bad_start_up_input_is_one_clear_line(run_driver, args: list[str],
                                              expected: str) -> None:
    run = run_driver(*args)
    assert run.returncode == 2, run.stderr
    assert "Traceback" not in run.stderr + run.stdout
    errors = [line for line in run.stderr.splitlines() if "] error:" in line]
    assert len(errors) == 1 and expected in errors[0], run.stderr


def test_a_folder_with_an_image_of_the_wrong_size_is_named_at_start(
        run_driver, tmp_path: Path) -> None:
    sizes = [(H, W)] * 4 + [(H, W + 4)] + [(H, W)] * 2
    folder = _folder(tmp_path / "odd", sizes)
    run = run_driver("-p", "camera:=folder", "-p", f"camera_folder:={folder}")
    assert run.returncode == 2
    errors = [line for line in run.stderr.splitlines() if "] error:" in line]
    assert len(errors) == 1 and "led_4.png (LED 4)" in errors[0], run.stderr
