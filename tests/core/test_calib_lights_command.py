"""Tests of the calibrate_lights command (fingerps_calib.calibrate_lights_command).

Perspective: a folder of the simulated rig's sphere images with its camera_info YAML;
truth as in test_sphere_calibration_sim.py (specular point -> LED). Orthographic: analytic
chrome-sphere images with a mask, as a public data set would give.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from fingerps_calib.calibrate_lights_command import main
from fingerps_calib.intrinsics.camera_info_yaml import CameraIntrinsics, save_camera_info
from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.photometric.frames import optical_to_ps


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig())


@pytest.fixture(scope="module")
def sphere_images(rig) -> np.ndarray:
    return rig.render_burst(Scene.SPHERE, seed=40)


def _folder(path: Path, images: np.ndarray, *, names: list[str] | None = None) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    names = names or [f"sphere_{k:02d}.png" for k in range(len(images))]
    for name, image in zip(names, images, strict=True):
        cv2.imwrite(str(path / name), image)
    (path / "filenames.txt").write_text("# LED order\n" + "\n".join(names) + "\n\n")
    return path


def _camera_info(path: Path, rig: SimulatedRig, *, width: int | None = None) -> Path:
    save_camera_info(path, CameraIntrinsics(
        width=width or rig.camera.width, height=rig.camera.height,
        camera_matrix=rig.camera_matrix, distortion_model="plumb_bob",
        distortion=np.zeros(5), camera_name="fingerps_sim"))
    return path


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_perspective_folder_gives_diligent_light_directions(rig, sphere_images, tmp_path,
                                                            capsys):
    folder = _folder(tmp_path / "sphere", sphere_images)
    info = _camera_info(tmp_path / "camera_info.yaml", rig)
    assert main([str(folder), "--radius", "0.004", "--camera-info", str(info)]) == 0
    assert "wrote" in capsys.readouterr().out
    rows = np.loadtxt(folder / "light_directions.txt")
    assert rows.shape == (rig.led_count, 3)
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-7)
    assert np.all(rows[:, 2] > 0)  # DiLiGenT: z towards the camera
    specular = np.stack([rig.sphere.specular_point(p) for p in rig.led_positions_optical])
    errors = _angles_deg(rows, optical_to_ps(rig.led_positions_optical - specular))
    assert np.all(errors < 0.3), errors
    report = yaml.safe_load((folder / "light_calibration_report.yaml").read_text())
    assert report["ok"] is True and report["problems"] == []
    assert report["method"].startswith("perspective")
    np.testing.assert_allclose(report["sphere_center_m"], rig.config.sphere.center_optical_m,
                               atol=0.2e-3)
    assert report["edge_rms_px"] < 0.3
    assert [led["file"] for led in report["leds"]] == [f"sphere_{k:02d}.png" for k in range(7)]
    assert all(led["highlight_residual_px"] < 0.3 for led in report["leds"])
    picture = cv2.imread(str(folder / "light_calibration.png"))
    assert picture is not None and picture.shape[1] == 960
    # A second run does not overwrite light_directions.txt without --force.
    before = (folder / "light_directions.txt").read_bytes()
    assert main([str(folder), "--radius", "0.004", "--camera-info", str(info)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (folder / "light_directions.txt").read_bytes() == before


def test_orthographic_folder_with_a_mask(tmp_path):
    h, w, rho, cu, cv = 240, 320, 60.0, 158.4, 121.2
    vv, uu = np.mgrid[0:h, 0:w]
    disc = np.clip(rho - np.hypot(uu - cu, vv - cv) + 0.5, 0, 1)
    lights = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86], [0.0, -0.6, 0.8],
                       [0.2, 0.45, 0.87]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    normals = lights + np.array([0.0, 0.0, 1.0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    images = []
    for n in normals:  # 16-bit, as DiLiGenT's PNGs
        u0, v0 = cu + rho * n[0], cv - rho * n[1]
        blob = np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 1.5**2))
        images.append(np.round(4000 * disc + 50000 * blob).astype(np.uint16))
    folder = _folder(tmp_path / "chrome", np.stack(images),
                     names=[f"{k + 1:03d}.png" for k in range(4)])
    cv2.imwrite(str(folder / "mask.png"), (255 * (disc >= 0.5)).astype(np.uint8))
    out = tmp_path / "out"
    assert main([str(folder), "--out", str(out)]) == 0
    rows = np.loadtxt(out / "light_directions.txt")
    np.testing.assert_allclose(rows, lights, atol=5e-3)
    report = yaml.safe_load((out / "light_calibration_report.yaml").read_text())
    assert report["method"].startswith("orthographic") and report["mask"] is True
    assert report["circle_radius_px"] == pytest.approx(rho, abs=0.6)


def test_a_failed_calibration_writes_the_report_not_the_directions(rig, sphere_images,
                                                                   tmp_path, capsys):
    images = sphere_images.copy()
    images[2] = rig.render(Scene.SPHERE, [], rng=np.random.default_rng(2))  # LED 2 dark
    folder = _folder(tmp_path / "sphere", images)
    info = _camera_info(tmp_path / "camera_info.yaml", rig)
    assert main([str(folder), "--radius", "0.004", "--camera-info", str(info)]) == 1
    err = capsys.readouterr().err
    assert "FAILED" in err and "LED 2: no highlight" in err
    assert not (folder / "light_directions.txt").exists()
    report = yaml.safe_load((folder / "light_calibration_report.yaml").read_text())
    assert report["ok"] is False and report["problems"][0].startswith("LED 2:")
    assert (folder / "light_calibration.png").exists()


def test_bad_input_exits_2_with_the_fix(rig, sphere_images, tmp_path, capsys):
    info = _camera_info(tmp_path / "camera_info.yaml", rig)

    def run(*args: str) -> str:
        assert main(list(args)) == 2
        return capsys.readouterr().err

    empty = tmp_path / "empty"
    empty.mkdir()
    assert "filenames.txt does not exist: list the sphere images" in run(str(empty))
    folder = _folder(tmp_path / "few", sphere_images[:2])
    (folder / "filenames.txt").write_text("sphere_00.png\nmissing.png\n")
    message = run(str(folder))
    assert "cannot read image" in message and "missing.png" in message
    small = _folder(tmp_path / "sizes", sphere_images[:2])
    cv2.imwrite(str(small / "sphere_01.png"), sphere_images[1][:400])
    assert "different sizes" in run(str(small))
    masked = _folder(tmp_path / "mask", sphere_images[:2])
    cv2.imwrite(str(masked / "mask.png"), np.zeros((10, 10), np.uint8))
    assert "give a mask of the images' size" in run(str(masked))
    good = _folder(tmp_path / "good", sphere_images[:2])
    assert "needs --radius" in run(str(good), "--camera-info", str(info))
    other = _camera_info(tmp_path / "other.yaml", rig, width=640)
    message = run(str(good), "--radius", "0.004", "--camera-info", str(other))
    assert "659x493" in message and "640x493" in message
    with pytest.raises(SystemExit):
        main([str(good), "--radius", "-1"])


def test_the_command_is_installed(installed):
    exe = installed("fingerps_calib", "calibrate_lights")
    done = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "filenames.txt" in done.stdout
