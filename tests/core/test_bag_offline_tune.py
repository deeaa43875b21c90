"""offline_tune on a small synthetic DiLiGenT-layout folder (a ridged dome rendered
Lambertian under 8 known lights, with mask.png and normal_gt.npy) and on a bag without
calibration."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
from rclpy.serialization import serialize_message

from fingerps_msgs.msg import Burst
from fingerps_recon.offline.offline_tune import main
from fingerps_recon.sessions.session_bag import SessionBagWriter

SIZE = (72, 88)
LIGHTS = 8


def _ridged_dome(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (PS frame) of a dome with concentric ridges (period 6 px), and its mask."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = u - (width - 1) / 2, -(v - (height - 1) / 2)
    r = np.hypot(x, y)
    radius = 0.45 * min(height, width)
    mask = r < radius
    z = np.sqrt(np.clip(radius**2 - r**2, 0, None)) + 0.6 * np.sin(2 * np.pi * r / 6.0)
    gy, gx = np.gradient(np.where(mask, z, 0.0))
    n = np.stack([-gx, gy, np.ones_like(gx)], axis=2)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return np.where(mask[..., None], n, 0.0), mask


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("dome")
    normals, mask = _ridged_dome(*SIZE)
    azimuth = np.linspace(0, 2 * np.pi, LIGHTS, endpoint=False)
    tilt = np.deg2rad(np.resize([25.0, 40.0], LIGHTS))
    lights = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                       np.cos(tilt)], axis=1)
    names = []
    for k, light in enumerate(lights):
        shade = np.clip(normals @ light, 0, None) * mask * 250
        names.append(f"{k:03d}.png")
        cv2.imwrite(str(path / names[-1]), np.round(shade).astype(np.uint8))
    (path / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(path / "light_directions.txt", lights)
    cv2.imwrite(str(path / "mask.png"), mask.astype(np.uint8) * 255)
    np.save(path / "normal_gt.npy", normals)
    return path


def test_sweep_over_a_folder_writes_outputs_table_and_contact_sheet(
        folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "tune"
    assert main([str(folder), "--out", str(out), "--model", "lambert",
                 "--w", "5,9", "--k", "1,4", "--ridge-period", "6"]) == 0
    captured = capsys.readouterr()
    assert "1/1 solves" in captured.err  # the progress bar
    assert "ridge_visibility" in captured.out and "lambert_w9_k4" in captured.out
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["setting"] for r in rows] == ["lambert_w5_k1", "lambert_w5_k4",
                                            "lambert_w9_k1", "lambert_w9_k4"]
    for row in rows:  # 8-bit Lambertian rendering: the solve is near exact
        assert float(row["error_mean_deg"]) < 2.0
    visibility = {r["setting"]: float(r["ridge_visibility"]) for r in rows}
    plain = float(rows[0]["ridge_visibility_plain"])
    assert visibility["lambert_w5_k4"] > visibility["lambert_w5_k1"] > plain > 0
    model_dir = out / folder.name / "lambert"
    normals = np.load(model_dir / "normals.npy")
    assert normals.shape == (*SIZE, 3) and normals.dtype == np.float32
    assert {p.name for p in model_dir.iterdir()} >= {"normals.npy", "depth.npy", "cloud.ply",
                                                     "w5_k1", "w9_k4"}
    assert (model_dir / "w9_k4" / "normal_map.png").is_file()
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet.shape[1] > 4 * SIZE[1] * 2  # four tiles side by side


def test_bad_input_is_one_line_and_exit_code_2(folder: Path, tmp_path: Path, capsys) -> None:
    broken = tmp_path / "no_lights"
    broken.mkdir()
    for f in folder.iterdir():
        if f.name != "light_directions.txt":
            (broken / f.name).write_bytes(f.read_bytes())
    assert main([str(broken), "--out", str(tmp_path / "o1")]) == 2
    assert "light_directions.txt" in capsys.readouterr().err

    assert main([str(folder), "--out", str(tmp_path / "o2"), "--w", "4"]) == 2
    assert "w must be odd" in capsys.readouterr().err

    bag = tmp_path / "nocal"
    with SessionBagWriter(bag) as writer:
        writer.add_topic("/fingerps/burst", "fingerps_msgs/msg/Burst", offered_qos_yaml="[]")
        writer.write("/fingerps/burst", serialize_message(Burst(burst_id=1)), log_time_ns=1,
                     publish_time_ns=1)
    assert main([str(bag), "--out", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err
    assert "no light calibration" in err and "--calibration" in err


def test_the_sweep_runs_after_this_process_used_the_parallel_kernels(
        folder: Path, tmp_path: Path) -> None:
    # numba's worker threads, once started here, do not survive a fork(): the sweep's worker
    # processes must be fresh interpreters (before: BrokenProcessPool).
    from fingerps_recon.photometric.kernel_warm_up import warm_up_kernels

    warm_up_kernels()  # every parallel kernel has run in this process now
    out = tmp_path / "tune"
    assert main([str(folder), "--out", str(out), "--model", "lambert,hk", "--w", "5",
                 "--k", "1", "--jobs", "2"]) == 0
    assert len(list(csv.DictReader(open(out / "summary.csv")))) == 2
