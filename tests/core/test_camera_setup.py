"""camera_setup without ROS: the camera the settings ask for, the refusals of settings that do
not fit, the simulated finger's motion over a burst, and the calibration the camera
publishes (with what the log says)."""

from __future__ import annotations

from unittest.mock import Mock, call

import numpy as np
import pytest
from test_board_connection import said

from fingerps_calib.intrinsics.camera_info_url import store_camera_info
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics
from fingerps_driver.cameras.camera import SimulatedCamera
from fingerps_driver.cameras.camera_opencv import OpenCvCamera
from fingerps_driver.cameras.camera_setup import (
    FALLBACK_SOURCE,
    CameraBackend,
    CameraSettings,
    RigRenderer,
    SimSettings,
    how_to_calibrate,
    make_camera,
    open_calibration,
)
from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation import PinholeCamera, RigConfig, Scene, SimulatedRig

W, H = 96, 72
NODE, TOPIC = "/fingerps/driver", "/fingerps/image_raw"


def _lit() -> tuple[int, ...]:
    return (0,)


def _sim(**changes) -> CameraSettings:
    return CameraSettings(width=W, height=H, **changes)


def test_the_sim_camera_renders_the_rig_of_its_settings():
    camera, renderer = make_camera(_sim(sim=SimSettings(bit_depth=12)), _lit, emulated=True)
    assert isinstance(camera, SimulatedCamera) and isinstance(renderer, RigRenderer)
    assert (camera.width, camera.height, camera.encoding) == (W, H, "mono16")
    assert renderer.rig.config.sensor.bit_depth == 12 and renderer.scene is Scene.FINGER
    with camera:
        assert camera.grab(timeout_s=0.1).shape == (H, W)


def test_a_v4l2_camera_is_made_from_its_settings_without_opening_it():
    camera, renderer = make_camera(
        CameraSettings(backend=CameraBackend.V4L2, device="/dev/video99", exposure_s=0.02),
        _lit, emulated=False)
    assert isinstance(camera, OpenCvCamera) and renderer is None
    assert CameraSettings(backend=CameraBackend.V4L2, device="/dev/x").device_name == "/dev/x"
    assert CameraSettings(backend=CameraBackend.FOLDER, folder="/f").device_name == "/f"
    assert CameraSettings().device_name == ""


@pytest.mark.parametrize(("settings", "emulated", "message"), [
    (CameraSettings(width=W), True, "set camera_width and camera_height both, or neither"),
    (CameraSettings(backend=CameraBackend.FOLDER), True,
     "camera:=folder needs camera_folder (a DiLiGenT-layout folder with filenames.txt)"),
    (_sim(pixel_format="mono16"), True,
     "camera_pixel_format mono16 does not match sim.bit_depth 8 (mono8); leave "
     "camera_pixel_format empty or change sim.bit_depth"),
    (_sim(led_count=8), True, "the simulated rig has 7 LEDs; set led_count to that"),
    (_sim(), False, "camera:=sim needs port:=sim (the built-in board emulator) or, with a "
                    "board_emulator process, sim.board_control:=<its --control socket>"),
])
def test_settings_that_do_not_fit_are_one_line(settings, emulated, message):
    with pytest.raises(FingerpsDriverError) as caught:
        make_camera(settings, _lit, emulated=emulated)
    assert str(caught.value) == message


def _renderer(motion_px=(4.0, -2.0), motion_bursts=0) -> RigRenderer:
    rig = SimulatedRig(RigConfig(camera=PinholeCamera(width=W, height=H)))
    return RigRenderer(rig, SimSettings(seed=3, motion_px=motion_px,
                                        motion_bursts=motion_bursts))


def _expected(rig: SimulatedRig, shifts: list[tuple[float, float]]) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [rig.render(Scene.FINGER, [0], rng=rng, finger_shift_px=s) for s in shifts]


def test_frame_i_of_n_shows_the_finger_moved_by_i_over_n():
    renderer = _renderer()
    renderer.start_burst(2)
    frames = [renderer.render([0]) for _ in range(4)]  # two LEDs, the repeat, one more
    expected = _expected(renderer.rig, [(0.0, 0.0), (2.0, -1.0), (4.0, -2.0), (4.0, -2.0)])
    for frame, truth in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(frame, truth)


def test_motion_limited_to_some_bursts_counts_from_its_setting():
    renderer = _renderer(motion_bursts=1)
    renderer.start_burst(1)  # set at start, not since: still (as the driver always did)
    frames = [renderer.render([0])]
    renderer.set_motion([6.0, 0.0], 1)
    for _ in range(2):  # moves in the first burst only: its frame 1 of 1 moved by all
        renderer.start_burst(1)
        frames += [renderer.render([0]), renderer.render([0])]
    expected = _expected(renderer.rig, [(0.0, 0.0), (0.0, 0.0), (6.0, 0.0), (0.0, 0.0),
                                        (0.0, 0.0)])
    for frame, truth in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(frame, truth)


def test_the_sphere_and_the_finger_are_rebuilt_from_the_rig_in_use():
    renderer = _renderer()
    moved = renderer.moved_sphere([0.0, 0.0, 0.1])
    assert moved.config.sphere.center_optical_m == (0.0, 0.0, 0.1)
    assert moved.camera.width == W
    posed = renderer.posed_finger({"roll_deg": 10.0, "identity": 2})
    assert posed.config.finger.roll_deg == 10.0 and posed.config.finger.identity == 2
    assert posed.camera.width == W
    assert renderer.rig.config.finger.roll_deg == 0.0  # the caller swaps it in


def _camera_and_rig():
    camera, renderer = make_camera(_sim(), _lit, emulated=True)
    return camera, renderer.rig


def test_without_a_file_the_sim_camera_publishes_the_rig_s_intrinsics(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    camera, rig = _camera_and_rig()
    log = Mock()
    manager = open_calibration(_sim(), camera, rig, node_name=NODE, image_topic=TOPIC, log=log)
    assert manager.current.source == FALLBACK_SOURCE
    np.testing.assert_array_equal(manager.current.intrinsics.camera_matrix, rig.camera_matrix)
    assert [name for name, _, _ in log.method_calls] == ["info"]
    assert log.method_calls[0].args[0].startswith(f"no camera calibration at {tmp_path}/ros_home/"
                                      "camera_info/fingerps_sim.yaml: publishing "
                                      f"{FALLBACK_SOURCE}; to calibrate run `ros2 run ")
    assert log.method_calls[0].args[0].endswith(how_to_calibrate(_sim(), node_name=NODE,
                                                     image_topic=TOPIC))


def test_a_missing_file_named_by_url_is_a_warning(tmp_path):
    camera, rig = _camera_and_rig()
    log = Mock()
    url = f"file://{tmp_path}/cam.yaml"
    open_calibration(_sim(camera_info_url=url), camera, rig, node_name=NODE,
                     image_topic=TOPIC, log=log)
    assert said(log, "warning", f"no camera calibration at {tmp_path}/cam.yaml: publishing")
    assert f"--camera-info-url '{url}'" in log.method_calls[0].args[0]


def test_a_stored_calibration_is_loaded(tmp_path):
    camera, rig = _camera_and_rig()
    path = tmp_path / "cam.yaml"
    k = np.array([[500.0, 0, 48], [0, 500.0, 36], [0, 0, 1]])
    store_camera_info(path, CameraIntrinsics(W, H, k, "plumb_bob", np.zeros(5), "fingerps_sim"))
    log = Mock()
    manager = open_calibration(_sim(camera_info_file=str(path)), camera, rig, node_name=NODE,
                               image_topic=TOPIC, log=log)
    assert manager.current.source == str(path)
    assert log.method_calls == [call.info(f"camera calibration: {path}")]


@pytest.mark.parametrize(("changes", "message"), [
    ({"camera_info_url": "file:///a.yaml", "camera_info_file": "/b.yaml"},
     "set camera_info_url or camera_info_file, not both"),
    ({"camera_info_file": "/nonexistent/cam.yaml"},
     "no camera calibration at /nonexistent/cam.yaml"),
])
def test_calibration_settings_that_cannot_be_used_are_one_line(changes, message):
    camera, rig = _camera_and_rig()
    with pytest.raises(FingerpsDriverError) as caught:
        open_calibration(_sim(**changes), camera, rig, node_name=NODE, image_topic=TOPIC,
                         log=Mock())
    assert str(caught.value) == message


def test_the_calibration_hint_names_the_node_and_the_topic():
    hint = how_to_calibrate(_sim(camera_name="cam_1", camera_info_url="package://p/c.yaml"),
                            node_name=NODE, image_topic=TOPIC)
    assert f"-r image:={TOPIC} -r camera/set_camera_info:={NODE}/set_camera_info`" in hint
    assert hint.endswith("--camera-name cam_1 --camera-info-url 'package://p/c.yaml'`")
