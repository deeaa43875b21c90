"""Tests of fingerps_calib.calibration_keeper: the calibration in force, without a ROS graph.

The sphere and white-target images are rendered by the simulated rig (default RigConfig:
4 mm ball at 94 mm, f = 3000 px); the keeper gets them as `Shots`, logs into a list and
"publishes" into lists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from fingerps_calib.calibration_camera import DriverCameraInfo
from fingerps_calib.calibration_keeper import (
    CalibrationKeeper,
    CalibrationSettings,
    Shots,
    open_calibration_dir,
)
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics
from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig

STAMP = 1_760_000_000_000_000_000
SETTINGS = CalibrationSettings()


class _Log:
    """Records the lines logged, as (level, text)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str) -> None:
        self.lines.append(("info", message))

    def warning(self, message: str) -> None:
        self.lines.append(("warning", message))

    def error(self, message: str) -> None:
        self.lines.append(("error", message))

    def text(self, level: str) -> str:
        return "\n".join(m for lv, m in self.lines if lv == level)


class _Keeper:
    """A keeper with its log and what it published."""

    def __init__(self, directory: Path | None, *, file_camera: CameraIntrinsics | None = None,
                 stamp: int = STAMP) -> None:
        self.log = _Log()
        self.lights: list[tuple[object, list[float]]] = []
        self.flats: list[object] = []
        self.keeper = CalibrationKeeper(
            directory, file_camera=file_camera, log=self.log, now_ns=lambda: stamp,
            publish_lights=lambda record, intensities: self.lights.append(
                (record, intensities)),
            publish_flat=self.flats.append)


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig())


def _render(rig: SimulatedRig, scene: Scene, seed: int) -> np.ndarray:
    return rig.render_burst(scene, seed=seed)


@pytest.fixture(scope="module")
def sphere(rig) -> np.ndarray:
    return _render(rig, Scene.SPHERE, 0)


@pytest.fixture(scope="module")
def white(rig) -> np.ndarray:
    return _render(rig, Scene.WHITE_TARGET, 50)


def _info(rig: SimulatedRig, *, k: np.ndarray | None = None) -> DriverCameraInfo:
    return DriverCameraInfo(
        k=np.asarray(rig.camera_matrix, float).ravel() if k is None else k, d=np.zeros(5),
        distortion_model="plumb_bob", width=rig.camera.width, height=rig.camera.height,
        frame_id="fingerps_camera_optical_frame")


def _shots(images: np.ndarray, info: DriverCameraInfo | None, *,
           dark: np.ndarray | None = None):
    return lambda: Shots(images=images, encoding="mono8", frame_id="", dark=dark,
                         camera_info=info)


def test_a_light_calibration_is_put_in_force_saved_and_published(tmp_path, rig, sphere):
    k = _Keeper(tmp_path)
    answer = k.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.0,
                                       add_placement=False, settings=SETTINGS)
    assert answer.success, answer.message
    assert answer.message.startswith(f"{rig.led_count} LEDs calibrated from 1 sphere "
                                     "placement(s); sphere centre (")
    assert f"; saved to {tmp_path / 'lights.yaml'}" in answer.message
    assert f"; picture {tmp_path / 'lights.png'}" in answer.message
    assert k.log.lines == [("info", answer.message)]
    assert k.keeper.lights is answer.lights and k.keeper.flat is None
    assert answer.relative_intensities == (1.0,) * rig.led_count
    assert k.lights == [(answer.lights, [1.0] * rig.led_count)]
    assert answer.lights.frame_id == "fingerps_camera_optical_frame"
    assert answer.lights.camera_name == "fingerps_sim" and answer.lights.date.endswith("Z")
    assert yaml.safe_load((tmp_path / "lights.yaml").read_text())["camera_name"] \
        == "fingerps_sim"
    assert k.keeper.in_force() == f"in force: lights of {answer.lights.date}, no flat field"


def test_the_request_radius_is_checked_before_any_capture(tmp_path):
    k = _Keeper(tmp_path)

    def capture() -> Shots:
        raise AssertionError("no capture for a bad radius")
    for radius in (1e-300, -1.0, np.inf, np.nan, 1.0):
        answer = k.keeper.calibrate_lights(capture, sphere_radius_m=radius,
                                           add_placement=False, settings=SETTINGS)
        assert not answer.success
        assert f"sphere_radius {radius!r} m in the request" in answer.message
        assert "between 0.0005 and 0.05 m (0.5-50 mm)" in answer.message
        assert "or 0 for calib_node's sphere_radius (0.004 m)" in answer.message
    assert k.log.text("error").count("light calibration refused: sphere_radius") == 5


def test_without_intrinsics_the_lights_are_refused_with_the_fix(tmp_path, rig, sphere):
    k = _Keeper(None)
    answer = k.keeper.calibrate_lights(_shots(sphere, None), sphere_radius_m=0.004,
                                       add_placement=False, settings=SETTINGS)
    assert not answer.success
    assert answer.message.startswith("no camera intrinsics: start driver_node (its "
                                     "camera_info) or calib_node's camera_info_file")
    assert "calibrate_camera" in answer.message
    zero = k.keeper.calibrate_lights(_shots(sphere, _info(rig, k=np.zeros(9))),
                                     sphere_radius_m=0.004, add_placement=False,
                                     settings=SETTINGS)
    assert zero.message.startswith("the driver's camera_info has no intrinsics (K = 0)")


def test_images_of_another_size_than_the_intrinsics_are_refused(tmp_path, rig, sphere):
    file_camera = CameraIntrinsics(
        width=rig.camera.width, height=rig.camera.height, camera_matrix=rig.camera_matrix,
        distortion_model="plumb_bob", distortion=np.zeros(5), camera_name="cam")
    k = _Keeper(tmp_path, file_camera=file_camera)
    answer = k.keeper.calibrate_lights(_shots(sphere[:, :400, :600], None),
                                       sphere_radius_m=0.004, add_placement=False,
                                       settings=SETTINGS)
    assert not answer.success
    assert answer.message.startswith(
        f"the images are 600x400 but the intrinsics (camera_info_file (cam)) are for "
        f"{rig.camera.width}x{rig.camera.height}")
    tiny = k.keeper.calibrate_lights(_shots(sphere[:, :32, :32], None), sphere_radius_m=0.004,
                                     add_placement=False, settings=SETTINGS)
    assert tiny.message.startswith("frames are 32x32 px; a calibration needs whole camera "
                                   "frames of at least 64x64")


def test_a_refused_calibration_leaves_the_one_in_force(tmp_path, rig, sphere):
    k = _Keeper(tmp_path)
    good = k.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.004,
                                     add_placement=False, settings=SETTINGS)
    assert good.success, good.message
    saved = (tmp_path / "lights.yaml").read_bytes()
    empty = _render(rig, Scene.EMPTY, 70)
    refused = k.keeper.calibrate_lights(_shots(empty, _info(rig)), sphere_radius_m=0.004,
                                        add_placement=False, settings=SETTINGS)
    assert not refused.success and refused.lights is None
    assert "sphere not found" in refused.message
    assert f"[the calibration of {good.lights.date} stays in force]" in refused.message
    again = k.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.004,
                                      add_placement=True, settings=SETTINGS)
    assert not again.success and "too close together" in again.message
    assert f"[picture: {tmp_path / 'lights_rejected.png'}]" in again.message
    assert (tmp_path / "lights_rejected.png").stat().st_size > 10_000
    assert k.keeper.lights is good.lights and len(k.lights) == 1
    assert (tmp_path / "lights.yaml").read_bytes() == saved
    assert f"light calibration refused: {again.message}" in k.log.text("error")


def test_a_placement_of_another_led_count_is_not_added(tmp_path, rig, sphere):
    k = _Keeper(None)
    good = k.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.004,
                                     add_placement=False, settings=SETTINGS)
    assert good.success and "not saved (calibration_dir is empty)" in good.message
    fewer = k.keeper.calibrate_lights(_shots(sphere[:5], _info(rig)), sphere_radius_m=0.004,
                                      add_placement=True, settings=SETTINGS)
    assert not fewer.success
    assert fewer.message.startswith(
        f"add_placement: the calibration in force has {rig.led_count} LEDs, these images 5; "
        "calibrate with add_placement=false to start a new set of placements")


def test_a_flat_field_gives_the_lights_their_intensities(tmp_path, rig, sphere, white):
    k = _Keeper(tmp_path)
    lights = k.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.004,
                                       add_placement=False, settings=SETTINGS)
    dark = rig.render(Scene.WHITE_TARGET, [], rng=np.random.default_rng(49))
    flat = k.keeper.calibrate_flat_field(_shots(white, _info(rig), dark=dark),
                                         settings=SETTINGS)
    assert flat.success, flat.message
    assert flat.message.startswith(f"{rig.led_count} flat-field maps; relative intensities ")
    assert f"; saved to {tmp_path / 'flat_field.yaml'}" in flat.message
    assert f"; picture {tmp_path / 'flat_field.png'}" in flat.message
    assert k.flats == [flat.flat] and k.keeper.flat is flat.flat
    assert flat.flat.frame_id == "fingerps_camera_optical_frame"
    republished, intensities = k.lights[-1]
    assert republished is lights.lights and len(k.lights) == 2
    np.testing.assert_allclose(intensities, flat.flat.relative_intensities)
    assert k.keeper.intensities(rig.led_count) == intensities

    not_flat = k.keeper.calibrate_flat_field(
        _shots(_render(rig, Scene.FINGER, 95), _info(rig)), settings=SETTINGS)
    assert not not_flat.success and "not flat and uniform" in not_flat.message
    assert f"[the flat field of {flat.flat.date} stays in force]" in not_flat.message
    assert k.keeper.flat is flat.flat and len(k.flats) == 1
    assert f"flat-field calibration refused: {not_flat.message}" in k.log.text("error")


def test_white_target_frames_of_another_size_are_refused(rig, white):
    k = _Keeper(None)
    answer = k.keeper.calibrate_flat_field(_shots(white[:, :64, :64], _info(rig)),
                                           settings=SETTINGS)
    assert not answer.success
    assert answer.message.startswith(
        f"the white-target frames are 64x64, the camera's images (the driver's camera_info) "
        f"{rig.camera.width}x{rig.camera.height}")
    dark = k.keeper.calibrate_flat_field(_shots(white, None, dark=np.zeros((64, 64))),
                                         settings=SETTINGS)
    assert dark.message.startswith(
        f"the dark frame is 64x64, the images {rig.camera.width}x{rig.camera.height}")


def test_the_saved_calibration_is_loaded_for_the_same_camera_only(tmp_path, rig, sphere,
                                                                  white):
    first = _Keeper(tmp_path)
    lights = first.keeper.calibrate_lights(_shots(sphere, _info(rig)), sphere_radius_m=0.004,
                                           add_placement=False, settings=SETTINGS)
    flat = first.keeper.calibrate_flat_field(_shots(white, _info(rig)), settings=SETTINGS)
    assert lights.success and flat.success

    again = _Keeper(tmp_path)
    again.keeper.load_saved("fingerps_sim")
    assert again.keeper.lights.date == lights.lights.date
    assert again.keeper.flat.date == flat.flat.date
    assert len(again.flats) == 1 and len(again.lights) == 1
    np.testing.assert_allclose(again.lights[0][1], flat.flat.relative_intensities)
    info = again.log.text("info")
    assert f"loaded the flat field of {flat.flat.date} ({rig.led_count} maps " in info
    assert f"from {tmp_path / 'lights.yaml'}; published" in info

    other = _Keeper(tmp_path)
    other.keeper.load_saved("kiosk_2")
    assert other.keeper.lights is None and other.keeper.flat is None
    assert other.lights == [] and other.flats == []
    warning = other.log.text("warning")
    assert (f"saved flat field in {tmp_path} is for camera 'fingerps_sim', this node's "
            "camera_name is 'kiosk_2': not loaded; recalibrate") in warning
    assert f"saved light calibration in {tmp_path} is for camera 'fingerps_sim'" in warning

    (tmp_path / "lights.yaml").write_text("format: fingerps_light_calibration/1\nleds: [\n")
    damaged = _Keeper(tmp_path)
    damaged.keeper.load_saved("fingerps_sim")
    assert damaged.keeper.lights is None and damaged.keeper.flat is not None
    assert "saved light calibration not loaded: " in damaged.log.text("error")


def test_the_calibration_dir_is_made_or_refused_with_the_fix(tmp_path):
    assert open_calibration_dir("") is None
    made = open_calibration_dir(str(tmp_path / "a" / "b"))
    assert made == tmp_path / "a" / "b" and made.is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("a file, not a directory")
    with pytest.raises(FingerpsCalibError, match=r"^calibration_dir .*writable directory"):
        open_calibration_dir(str(blocker / "calibration"))
