"""calib_node end to end over DDS, without a driver: images in the requests (rendered here by
the simulated rig at several sphere positions), intrinsics from camera_info_file.

- Two sphere placements are combined (add_placement) into LED positions and directions from
  the reference point (the default: the rig's fingertip apex), saved with their picture;
  the node restarted on the same calibration_dir publishes the same calibration (to late
  joiners: transient-local) and a third placement adds to the restored two.
- Bad input of every kind listed in the issue is refused with success=false and a message
  naming the fault and the fix; the calibration in force stays, its files untouched.
- A damaged or foreign saved calibration is not loaded, and the node still starts.
"""

from __future__ import annotations

import functools
import signal
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.node import Node

from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, save_camera_info
from fingerps_driver.simulation import MirrorSphere, RigConfig, Scene, SensorModel, SimulatedRig
from fingerps_msgs.msg import FlatField, LightCalibration, TaggedFrame
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import array_to_image, image_to_array

NS = "/" + topics.NAMESPACE
LIGHTS_TOPIC = f"{NS}/{topics.LIGHT_CALIBRATION}"
FLAT_TOPIC = f"{NS}/{topics.FLAT_FIELD}"
PLACES = {"A": (2.0e-3, -1.5e-3, 0.094), "B": (-5.5e-3, 2.0e-3, 0.094),
          "C": (5.0e-3, 2.5e-3, 0.098)}


def _frames(images: np.ndarray, *, dark: np.ndarray | None = None) -> list[TaggedFrame]:
    count = len(images)
    frames = [TaggedFrame(burst_id=1, led_index=k, led_count=count,
                          image=array_to_image(image, encoding="mono8"))
              for k, image in enumerate(images)]
    if dark is not None:
        frames.append(TaggedFrame(burst_id=1, led_index=TaggedFrame.LED_DARK, led_count=count,
                                  image=array_to_image(dark, encoding="mono8")))
    return frames


def _render(rig: SimulatedRig, scene: Scene, seed: int) -> np.ndarray:
    return rig.render_burst(scene, seed=seed)


def _sphere(place: str, seed: int = 0, *, sensor: SensorModel | None = None,
            **sphere) -> np.ndarray:
    config = RigConfig(sphere=MirrorSphere(center_optical_m=PLACES[place], **sphere),
                       sensor=sensor or SensorModel())
    return _render(SimulatedRig(config), Scene.SPHERE, seed)


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig())


def _camera_info_file(path: Path, rig: SimulatedRig) -> Path:
    save_camera_info(path, CameraIntrinsics(
        width=rig.camera.width, height=rig.camera.height, camera_matrix=rig.camera_matrix,
        distortion_model="plumb_bob", distortion=np.zeros(5), camera_name="fingerps_sim"))
    return path


class _Calib:
    """A calib_node process and the test node's clients of it."""

    def __init__(self, ros_node: Node, start_node, spin_until, call_service, *args: str) -> None:
        self.node, self.spin_until = ros_node, spin_until
        self.call = functools.partial(call_service, timeout=60.0)  # (client, request)
        self.process = start_node("fingerps_calib", "calib_node", "--ros-args", *args)
        self.process.wait_in_graph(ros_node, "calib", NS)
        self.lights = ros_node.create_client(CalibrateLights, f"{NS}/{topics.CALIBRATE_LIGHTS}")
        self.flat = ros_node.create_client(CalibrateFlatField,
                                           f"{NS}/{topics.CALIBRATE_FLAT_FIELD}")

    def calibrate_lights(self, images: np.ndarray, *, add: bool = False, radius: float = 0.004):
        return self.call(self.lights, CalibrateLights.Request(
            sphere_radius=radius, frames=_frames(images), add_placement=add))

    def calibrate_flat(self, images: np.ndarray, dark: np.ndarray | None = None):
        return self.call(self.flat, CalibrateFlatField.Request(frames=_frames(images,
                                                                              dark=dark)))

    def in_force(self, msg_type, topic: str, *, timeout: float = 20.0):
        """What a late joiner receives (transient-local), or None within ``timeout``."""
        received: list = []
        sub = self.node.create_subscription(msg_type, topic, received.append,
                                            qos.CALIBRATION_QOS)
        try:
            self.spin_until(lambda: received, f"a {msg_type.__name__}", timeout=timeout)
        except pytest.fail.Exception:
            if timeout > 5.0:
                raise
        finally:
            self.node.destroy_subscription(sub)
        return received[-1] if received else None

    def stop(self) -> None:
        self.process.send_signal(signal.SIGINT)
        assert self.process.wait() == 0, self.process.output
        assert "Traceback" not in self.process.output


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _vectors(points) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in points])


def test_placements_are_combined_saved_and_reloaded(ros_node, start_node, spin_until,
                                                    call_service, tmp_path, rig):
    directory = tmp_path / "calibration"
    args = ("-p", f"calibration_dir:={directory}",
            "-p", f"camera_info_file:={_camera_info_file(tmp_path / 'cam.yaml', rig)}")
    calib = _Calib(ros_node, start_node, spin_until, call_service, *args)

    first = calib.calibrate_lights(_sphere("A"))
    assert first.success, first.message
    assert first.calibration.placements == 1 and len(first.calibration.led_positions) == 0
    second = calib.calibrate_lights(_sphere("B", seed=10), add=True)
    assert second.success, second.message
    lights = second.calibration
    assert lights.placements == 2 and len(lights.led_positions) == rig.led_count
    apex = np.asarray(rig.config.finger.apex_optical_m)
    errors = _angles_deg(_vectors(lights.directions), rig.led_positions_optical - apex)
    print(f"\ndirection errors from the apex, 2 placements (deg) {np.round(errors, 3).tolist()}")
    assert np.all(errors < 0.3), errors
    positions = _vectors(lights.led_positions)
    assert np.all(np.linalg.norm(positions - rig.led_positions_optical, axis=1) < 3e-3)
    assert "triangulated" in second.message
    assert f"saved to {directory / 'lights.yaml'}" in second.message
    assert f"picture {directory / 'lights.png'}" in second.message
    saved = yaml.safe_load((directory / "lights.yaml").read_text())
    assert saved["camera_name"] == "fingerps_sim" and len(saved["placements"]) == 2
    assert saved["date"].endswith("Z") and "led_position_residual_mm_max" in saved["fit"]
    assert (directory / "lights.png").stat().st_size > 10_000

    white = _render(rig, Scene.WHITE_TARGET, 50)
    flat = calib.calibrate_flat(white, dark=rig.render(Scene.WHITE_TARGET, [],
                                                       rng=np.random.default_rng(49)))
    assert flat.success, flat.message
    assert (directory / "flat_field.png").exists()
    assert len(list(directory.glob("flat_field_*.npz"))) == 1
    assert "flat_field.png" in calib.process.output  # the log names the picture

    # A refused calibration changes nothing on disk.
    files = {p.name: p.read_bytes() for p in directory.iterdir() if p.suffix != ".png"}
    refused = calib.calibrate_lights(_render(rig, Scene.FINGER, 60), add=True)
    assert not refused.success and "stays in force" in refused.message, refused.message
    assert (directory / "lights_rejected.png").exists()
    refused_flat = calib.calibrate_flat(_render(rig, Scene.FINGER, 60))
    assert not refused_flat.success and "smooth lighting field" in refused_flat.message
    assert {p.name: p.read_bytes() for p in directory.iterdir() if p.suffix != ".png"} == files

    lights_before = calib.in_force(LightCalibration, LIGHTS_TOPIC)
    flat_before = calib.in_force(FlatField, FLAT_TOPIC)
    np.testing.assert_allclose(lights_before.relative_intensities,
                               flat.flat_field.relative_intensities)
    calib.stop()

    restarted = _Calib(ros_node, start_node, spin_until, call_service, *args)
    assert restarted.in_force(LightCalibration, LIGHTS_TOPIC) == lights_before
    flat_after = restarted.in_force(FlatField, FLAT_TOPIC)
    assert flat_after.header == flat_before.header
    assert flat_after.relative_intensities == flat_before.relative_intensities
    for a, b in zip(flat_after.maps, flat_before.maps, strict=True):
        np.testing.assert_array_equal(image_to_array(a), image_to_array(b))
    assert "loaded the light calibration" in restarted.process.output
    # The restored placements take a third.
    third = restarted.calibrate_lights(_sphere("C", seed=20), add=True)
    assert third.success, third.message
    assert third.calibration.placements == 3
    restarted.stop()


def test_bad_input_is_refused_and_the_calibration_stays(ros_node, start_node, spin_until,
                                                        call_service, tmp_path, rig):
    directory = tmp_path / "calibration"
    directory.mkdir()
    # A damaged light calibration and a flat field of another camera: neither is loaded.
    (directory / "lights.yaml").write_text("format: fingerps_light_calibration/1\nleds: [\n")
    calib = _Calib(ros_node, start_node, spin_until, call_service,
                   "-p", f"calibration_dir:={directory}",
                   "-p", f"camera_info_file:={_camera_info_file(tmp_path / 'c.yaml', rig)}",
                   "-p", "camera_name:=kiosk_1")
    assert calib.in_force(LightCalibration, LIGHTS_TOPIC, timeout=1.0) is None
    assert "saved light calibration not loaded" in calib.process.output

    good = calib.calibrate_lights(_sphere("A"))
    assert good.success, good.message
    saved = (directory / "lights.yaml").read_bytes()
    assert yaml.safe_load(saved)["camera_name"] == "kiosk_1"
    sphere = _sphere("A", seed=30)
    matte = SimulatedRig(RigConfig(sphere=MirrorSphere(center_optical_m=PLACES["A"],
                                                       specular_reflectance=0.0)))
    missing = sphere.copy()
    missing[3] = matte.render(Scene.SPHERE, [3], rng=np.random.default_rng(3))
    cut = SimulatedRig(RigConfig(sphere=MirrorSphere(center_optical_m=(-9.0e-3, 0.0, 0.094))))
    cases = [
        ("no sphere", lambda: calib.calibrate_lights(_render(rig, Scene.EMPTY, 70)),
         "sphere not found"),
        ("cut by the frame", lambda: calib.calibrate_lights(_render(cut, Scene.SPHERE, 80)),
         "cut by the image border (left): move it towards the middle"),
        ("highlight missing", lambda: calib.calibrate_lights(missing),
         "LED 3: no highlight"),
        ("saturated blob", lambda: calib.calibrate_lights(
            _sphere("A", psf_sigma_px=6.0, sensor=SensorModel(exposure_gain=4.0))),
         "saturated into a blob"),
        ("wrong radius", lambda: calib.calibrate_lights(sphere, radius=0.002),
         "is the radius right?"),
        ("wrong size", lambda: calib.calibrate_lights(sphere[:, :400, :600]),
         "the images are 600x400 but the intrinsics"),
        ("wrong count", lambda: calib.call(calib.lights, CalibrateLights.Request(
            sphere_radius=0.004, frames=_frames(sphere)[:5])), "got LEDs [0, 1, 2, 3, 4]"),
        ("placement too close", lambda: calib.calibrate_lights(sphere, add=True),
         "too close together"),
        ("saturated target", lambda: calib.calibrate_flat(np.clip(
            _render(rig, Scene.WHITE_TARGET, 90).astype(float) * 1.5, 0, 255).astype(
                np.uint8)), "saturated"),
        ("target not flat", lambda: calib.calibrate_flat(_render(rig, Scene.FINGER, 95)),
         "not flat and uniform"),
    ]
    for what, call, expected in cases:
        response = call()
        assert not response.success, what
        assert expected in response.message, (what, response.message)
        if "flat" not in what and "target" not in what:
            assert "stays in force" in response.message, (what, response.message)
    assert calib.process.running()
    assert calib.in_force(LightCalibration, LIGHTS_TOPIC) == good.calibration
    assert (directory / "lights.yaml").read_bytes() == saved
    assert calib.in_force(FlatField, FLAT_TOPIC, timeout=1.0) is None  # never made
    calib.stop()


def test_a_flat_field_of_another_camera_is_not_loaded(ros_node, start_node, spin_until,
                                                      call_service, tmp_path, rig):
    directory = tmp_path / "calibration"
    first = _Calib(ros_node, start_node, spin_until, call_service,
                   "-p", f"calibration_dir:={directory}",
                   "-p", "camera_name:=camera_a")
    flat = first.calibrate_flat(_render(rig, Scene.WHITE_TARGET, 100))
    assert flat.success, flat.message
    first.stop()
    second = _Calib(ros_node, start_node, spin_until, call_service,
                    "-p", f"calibration_dir:={directory}",
                    "-p", "camera_name:=camera_b")
    assert second.in_force(FlatField, FLAT_TOPIC, timeout=1.0) is None
    assert "is for camera 'camera_a'" in second.process.output
    # Neither a driver nor a camera_info_file: no intrinsics for the lights, and it says so.
    response = second.calibrate_lights(np.zeros((7, 32, 32), np.uint8))
    assert not response.success
    assert "no camera intrinsics" in response.message and "calibrate_camera" in response.message
    second.stop()


def test_an_unusable_calibration_dir_stops_the_node_with_one_line(start_node, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file, not a directory")
    calib = start_node("fingerps_calib", "calib_node", "--ros-args",
                       "-p", f"calibration_dir:={blocker / 'calibration'}")
    assert calib.wait() == 2
    lines = calib.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("[calib_node] error: calibration_dir")
    assert "writable directory" in lines[0]
