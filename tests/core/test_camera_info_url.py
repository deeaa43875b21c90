"""camera_info_manager's URL rules, the owner-only atomic store, the driver's calibration
manager (load, fall back, validate, store) and the CameraInfo conversion, without a graph."""

from __future__ import annotations

import math
import stat
from pathlib import Path

import numpy as np
import pytest
from ament_index_python.packages import get_package_share_directory
from sensor_msgs.msg import CameraInfo

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_conversion import (
    camera_info_to_intrinsics,
    intrinsics_to_camera_info,
)
from fingerps_calib.intrinsics.camera_info_url import (
    check_camera_name,
    resolve_camera_info_url,
    store_camera_info,
)
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, load_camera_info
from fingerps_driver.cameras.camera_info_manager import CameraInfoManager

W, H = 64, 48
K = np.array([[100.0, 0.0, 31.5], [0.0, 101.0, 23.5], [0.0, 0.0, 1.0]])


def _intrinsics(width: int = W, height: int = H, name: str = "cam",
                model: str = "plumb_bob", d: int = 5) -> CameraIntrinsics:
    return CameraIntrinsics(width, height, K, model, np.linspace(-0.1, 0.1, d), name)


@pytest.mark.parametrize(("url", "expected"), [
    ("", "/rh/camera_info/cam_1.yaml"),
    ("file:///etc/fingerps/${NAME}.yaml", "/etc/fingerps/cam_1.yaml"),
    ("FILE:///x/y.yaml", "/x/y.yaml"),  # scheme without regard to case, as camera_info_manager
    ("file://${ROS_HOME}/a.yaml", "/rh/a.yaml"),
    ("file:///a/$HOME/b.yaml", "/a/$HOME/b.yaml"),  # '$' without '{' stays
])
def test_urls_resolve_as_camera_info_manager_resolves_them(url: str, expected: str) -> None:
    env = {"ROS_HOME": "/rh", "HOME": "/home/u"}
    assert resolve_camera_info_url(url, "cam_1", environ=env) == Path(expected)


def test_ros_home_defaults_to_home_dot_ros() -> None:
    path = resolve_camera_info_url("", "cam", environ={"HOME": "/home/u"})
    assert path == Path("/home/u/.ros/camera_info/cam.yaml")


def test_package_urls_resolve_in_the_package_share() -> None:
    path = resolve_camera_info_url("package://fingerps_calib/config/${NAME}.yaml", "c")
    assert path == Path(get_package_share_directory("fingerps_calib")) / "config" / "c.yaml"


@pytest.mark.parametrize(("url", "expected"), [
    ("package://fingerps_no_such_package/c.yaml", "is not installed"),
    ("package://fingerps_calib", "package://<package>/<path"),
    ("flash:///", "not supported"),
    ("file://relative/c.yaml", "not a calibration URL"),
    ("http://host/c.yaml", "not a calibration URL"),
    ("/etc/c.yaml", "not a calibration URL"),
    ("file:///${USER}/c.yaml", "only ${NAME} and ${ROS_HOME}"),
])
def test_bad_urls_are_named_with_what_to_use(url: str, expected: str) -> None:
    with pytest.raises(FingerpsCalibError, match=expected.replace("$", r"\$")
                       .replace("{", r"\{").replace("}", r"\}")):
        resolve_camera_info_url(url, "cam")


@pytest.mark.parametrize("name", ["", "my-cam", "cam 1", "cam/1", "ĉam"])
def test_camera_names_follow_camera_info_manager(name: str) -> None:
    with pytest.raises(FingerpsCalibError, match="letters, digits and '_'"):
        check_camera_name(name)
    assert check_camera_name("Cam_01") == "Cam_01"


def test_store_is_owner_only_atomic_and_makes_its_folders(tmp_path: Path) -> None:
    path = tmp_path / "home" / "camera_info" / "cam.yaml"
    store_camera_info(path, _intrinsics())
    assert load_camera_info(path) == _intrinsics()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    store_camera_info(path, _intrinsics(name="other"))  # replaced, no temporary left behind
    assert load_camera_info(path).camera_name == "other"
    assert sorted(p.name for p in path.parent.iterdir()) == ["cam.yaml"]


def test_store_into_a_folder_that_cannot_be_made_says_so(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(FingerpsCalibError, match="cannot make the folder"):
        store_camera_info(blocker / "sub" / "cam.yaml", _intrinsics())


def _manager(tmp_path: Path, **kwargs) -> CameraInfoManager:
    args = dict(camera_name="cam", url=f"file://{tmp_path}/${{NAME}}.yaml", width=W,
                height=H)
    args.update(kwargs)
    return CameraInfoManager(**args)


def test_a_missing_file_falls_back_and_says_where_it_looked(tmp_path: Path) -> None:
    truth = _intrinsics()
    manager = _manager(tmp_path, fallback=truth, fallback_source="the rig")
    loaded = manager.load()
    assert loaded.intrinsics is truth and loaded.source == "the rig"
    assert loaded.problem == f"no camera calibration at {tmp_path}/cam.yaml"
    uncalibrated = _manager(tmp_path).load()
    assert uncalibrated.intrinsics is None and uncalibrated.source == "none (K = 0)"


@pytest.mark.parametrize(("content", "expected"), [
    (None, "is for 32x48 images but the camera delivers 64x48"),
    ("image_width: [", "camera info file"),
    ("image_width: 64\n", "camera info file"),
])
def test_a_bad_file_falls_back_with_the_reason(tmp_path: Path, content, expected) -> None:
    path = tmp_path / "cam.yaml"
    if content is None:
        store_camera_info(path, _intrinsics(width=32))
    else:
        path.write_text(content)
    loaded = _manager(tmp_path).load()
    assert loaded.intrinsics is None and expected in loaded.problem
    with pytest.raises(FingerpsCalibError, match=expected.split(" images")[0]):
        _manager(tmp_path, strict=True).load()


def test_a_file_of_another_camera_name_is_used_with_a_note(tmp_path: Path) -> None:
    store_camera_info(tmp_path / "cam.yaml", _intrinsics(name="bench"))
    loaded = _manager(tmp_path).load()
    assert loaded.intrinsics == _intrinsics(name="bench")
    assert "names camera 'bench', not 'cam'" in loaded.problem


def test_store_validates_writes_and_a_new_manager_loads_it(tmp_path: Path) -> None:
    manager = _manager(tmp_path, fallback=_intrinsics(), fallback_source="the rig")
    manager.load()
    stored = manager.store(_intrinsics(name="whatever"))
    assert stored.source == f"{tmp_path}/cam.yaml" and manager.current is stored
    assert stored.intrinsics == _intrinsics(name="cam")  # the driver's camera name
    again = _manager(tmp_path).load()
    assert again.intrinsics == _intrinsics(name="cam") and again.problem is None


@pytest.mark.parametrize(("intrinsics", "expected"), [
    (_intrinsics(width=W + 1), "is for 65x48 images but the camera delivers 64x48"),
    (_intrinsics(model="fisheye_x", d=4), "'fisheye_x' is not one of"),
])
def test_a_refused_calibration_changes_nothing(tmp_path: Path, intrinsics, expected) -> None:
    manager = _manager(tmp_path, fallback=_intrinsics(), fallback_source="the rig")
    before = manager.load()
    with pytest.raises(FingerpsCalibError, match=expected):
        manager.store(intrinsics)
    assert manager.current is before and not (tmp_path / "cam.yaml").exists()


def test_a_store_that_cannot_write_changes_nothing(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    manager = _manager(tmp_path, url=f"file://{tmp_path}/file/cam.yaml")
    before = manager.load()
    with pytest.raises(FingerpsCalibError, match="cannot make the folder"):
        manager.store(_intrinsics())
    assert manager.current is before


def test_bad_names_and_urls_are_refused_at_construction(tmp_path: Path) -> None:
    with pytest.raises(FingerpsCalibError, match="camera name"):
        _manager(tmp_path, camera_name="my-cam")
    with pytest.raises(FingerpsCalibError, match="not a calibration URL"):
        _manager(tmp_path, url="ftp://x/y.yaml")


def test_camera_info_round_trips_through_the_message() -> None:
    intrinsics = _intrinsics(model="rational_polynomial", d=8)
    info = intrinsics_to_camera_info(intrinsics, width=W, height=H)
    assert info.k[0] == 100.0 and len(info.d) == 8 and info.distortion_model == \
        "rational_polynomial"
    assert camera_info_to_intrinsics(info, camera_name="cam") == intrinsics
    empty = intrinsics_to_camera_info(None, width=W, height=H)
    assert (empty.width, empty.height) == (W, H) and not any(empty.k)
    with pytest.raises(FingerpsCalibError, match="is for 64x48 images"):
        intrinsics_to_camera_info(intrinsics, width=W + 2, height=H)


@pytest.mark.parametrize(("change", "expected"), [
    (lambda i: setattr(i, "k", [0.0] * 9), "K is all zeros"),
    (lambda i: setattr(i, "k", [math.nan, *i.k[1:]]), "non-finite"),
    (lambda i: setattr(i, "k", [-5.0, *i.k[1:]]), "fx, fy > 0"),
    (lambda i: setattr(i, "d", [0.1, 0.2]), "needs 5 coefficients"),
    (lambda i: setattr(i, "d", [0.1, math.inf, 0, 0, 0]), "non-finite"),
    (lambda i: setattr(i, "width", 0), "must be positive"),
])
def test_a_bad_camera_info_is_named(change, expected: str) -> None:
    info: CameraInfo = intrinsics_to_camera_info(_intrinsics(), width=W, height=H)
    change(info)
    with pytest.raises(FingerpsCalibError, match=expected):
        camera_info_to_intrinsics(info, camera_name="cam")
