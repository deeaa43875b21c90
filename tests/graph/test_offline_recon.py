"""offline_recon end to end: the installed executable on DiLiGenT-layout folders in tmp_path.

Folders: a Lambertian sphere rendered analytically under known lights (8-bit grey with
one-channel intensities; 16-bit colour with per-channel intensities and a coloured albedo,
the DiLiGenT case), and the simulated rig's finger (``SimulatedRig``, default HK skin, noiseless,
8 bit, no mask.png so the pipeline's finger mask is used); and the colour sphere under 96
lights, as many as every real DiLiGenT object has, with either model. Each run is a
subprocess of the installed script, as ``ros2 run fingerps_recon offline_recon`` would start it.

Measured: grey sphere mean angular error 0.076 deg (8-bit quantisation), colour sphere
0.0002 deg (2.3 deg if light_intensities.txt is left out, so the per-channel rule is seen);
the rig's finger 3.15 deg with Lambertian photometric stereo (near lights against the
distant-light model; cf. tests/core/test_pipeline.py), heights within 0.1 mm rms of the truth.
"""

from __future__ import annotations

import importlib.util
import json
import struct
import subprocess
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from analytic_surfaces import sphere_normals
from diligent_cases import CASES, spoil_folder
from record_readers import read_ansi_nist, read_iso_19794_2_2005, scalar

from fingerps_driver.simulation import Scene, SimulatedRig
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.records.wsq_image import MAX_RMS_ERROR, decode_wsq
from fingerps_recon.surface.ply import read_ply

SPHERE_MAX_MEAN_DEG = 1.0   # measured 0.076 (8-bit grey), 0.0002 (16-bit colour)
FINGER_MAX_MEAN_DEG = 5.0   # measured 3.15
SPHERE_96_MAX_MEAN_DEG = 0.01  # 96 lights, 16-bit colour: measured 0.0001 (both models)
OUTPUTS = ("normals.npy", "albedo.npy", "depth.npy", "normal_map.png", "cloud.ply",
           "report.json")


# ----------------------------------------------------------------------------- folders


def _lights(count: int) -> np.ndarray:
    """Unit directions in a DiLiGenT-like cone: azimuths around, 20-45 deg from the axis."""
    azimuth = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    tilt = np.deg2rad(np.resize([20.0, 35.0, 45.0], count))
    return np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                     np.cos(tilt)], axis=1)


def _write_sphere(folder: Path, *, colour16: bool, size: tuple[int, int] = (120, 140),
                  radius: float = 50.0, count: int = 12) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Render the sphere into a DiLiGenT-layout folder with mask.png and Normal_gt.mat."""
    folder.mkdir(parents=True)
    lights = _lights(count)
    normals, mask, height = sphere_normals(*size, radius_px=radius)
    shading = np.clip(np.einsum("hwc,kc->khw", normals, lights), 0.0, None)
    names = [f"{i + 1:03d}.png" for i in range(count)]
    if colour16:
        e = np.stack([np.linspace(0.7, 1.3, count), np.linspace(1.1, 0.9, count),
                      np.full(count, 0.6)], axis=1)
        rho = np.array([0.9, 0.6, 0.8])
        frames = shading[..., None] * e[:, None, None, :] * rho * 60000.0
        frames = np.clip(np.rint(frames), 0, 65535).astype(np.uint16)[..., ::-1]  # BGR
        np.savetxt(folder / "light_intensities.txt", e)
    else:
        e = np.linspace(0.8, 1.2, count)
        frames = np.clip(np.rint(shading * e[:, None, None] * 200.0), 0, 255).astype(np.uint8)
        np.savetxt(folder / "light_intensities.txt", e[:, None])
    for name, frame in zip(names, frames, strict=True):
        assert cv2.imwrite(str(folder / name), np.ascontiguousarray(frame))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)
    assert cv2.imwrite(str(folder / "mask.png"), mask.astype(np.uint8) * 255)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normals})
    return normals, mask, height


@pytest.fixture(scope="module")
def offline_recon(installed) -> Callable[..., subprocess.CompletedProcess]:
    """``offline_recon(*args)``: run the installed executable, return the finished process."""
    path = installed("fingerps_recon", "offline_recon")

    def run(*args: str | Path) -> subprocess.CompletedProcess:
        return subprocess.run([str(path), *map(str, args)], capture_output=True, text=True,
                              timeout=180)
    return run


def _ok(run: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert run.returncode == 0, f"offline_recon failed:\n{run.stdout}\n{run.stderr}"
    assert run.stderr == ""
    return run


def _mean_error(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.nanmean(angular_error_deg(normals, truth, mask=mask)))


# ----------------------------------------------------------------------------- spheres


def test_grey_8bit_sphere(offline_recon: Callable, tmp_path: Path) -> None:
    truth, mask, height = _write_sphere(tmp_path / "sphere", colour16=False)
    out = tmp_path / "out"
    run = _ok(offline_recon(tmp_path / "sphere", "--out", out))
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    assert not (out / "normals_enhanced.npy").exists()

    normals, albedo = np.load(out / "normals.npy"), np.load(out / "albedo.npy")
    depth = np.load(out / "depth.npy")
    assert normals.shape == (120, 140, 3) and normals.dtype == np.float32
    assert albedo.shape == (120, 140) and albedo.dtype == np.float32
    assert depth.shape == (120, 140) and depth.dtype == np.float32
    assert np.all(normals[~mask] == 0.0) and np.all(albedo[~mask] == 0.0)
    assert np.all(np.isnan(depth[~mask]))
    valid = np.linalg.norm(normals, axis=2) > 0
    assert valid.sum() == mask.sum()  # every sphere pixel has >= 3 lit lights
    error = _mean_error(normals, truth, mask)
    print(f"\ngrey sphere: mean angular error {error:.4f} deg")
    assert error < SPHERE_MAX_MEAN_DEG
    np.testing.assert_allclose(albedo[mask], 200.0, rtol=0.02)  # 200 grey levels per unit e

    # No --pixel-size: no metric scale, so no 500 ppi print, and the report says why.
    fingerprint = json.loads((out / "report.json").read_text())["fingerprint"]
    assert not fingerprint["made"] and "--pixel-size" in fingerprint["reason"]
    assert not (out / "fingerprint.png").exists() and not (out / "fingerprint.wsq").exists()
    # Depth: the sphere's height in pixel units (no --pixel-size), zero mean over the mask.
    expected = height - height[mask].mean()
    assert np.abs(depth[mask] - expected[mask]).mean() < 0.2  # measured 0.053 px
    assert abs(float(depth[mask].mean())) < 1e-3

    # The ground-truth evaluation, printed and in the report, matches ours.
    report = json.loads((out / "report.json").read_text())
    assert report["normal_gt"]["file"] == "Normal_gt.mat"
    assert report["normal_gt"]["mean_deg"] == pytest.approx(error, abs=1e-4)
    assert report["normal_gt"]["pixels"] == mask.sum()
    assert f"angular error vs Normal_gt.mat: mean {error:.3f} deg" in run.stdout
    assert (report["images"], report["height"], report["width"]) == (12, 120, 140)
    assert report["mask_pixels"] == report["valid_pixels"] == mask.sum()
    assert report["depth_unit"] == "px" and report["enhancement"] is None
    assert set(report["timings_ms"]) >= {"load", "reconstruct", "depth", "write", "total"}

    picture = cv2.cvtColor(cv2.imread(str(out / "normal_map.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(picture, normal_map_rgb(normals, mask=mask))

    # The cloud: one point per valid pixel, orthographic, optical frame, z = -height.
    cloud = read_ply(out / "cloud.ply")
    rows, cols = np.nonzero(mask)
    assert cloud["points"].shape == (mask.sum(), 3)
    np.testing.assert_allclose(cloud["points"][:, 0], cols - 69.5)
    np.testing.assert_allclose(cloud["points"][:, 1], rows - 59.5)
    np.testing.assert_allclose(cloud["points"][:, 2], -depth[rows, cols], atol=1e-5)
    np.testing.assert_allclose(cloud["intensity"], albedo[rows, cols])
    np.testing.assert_allclose(cloud["normals"], normals[rows, cols] * [1, -1, -1], atol=1e-6)


def test_colour_16bit_sphere_with_channel_intensities_and_enhancement(
        offline_recon: Callable, tmp_path: Path) -> None:
    truth, mask, height = _write_sphere(tmp_path / "sphere", colour16=True)
    out = tmp_path / "out"
    run = _ok(offline_recon(tmp_path / "sphere", "--out", out, "--w", "5",
                            "--pixel-size", "1e-4"))
    normals = np.load(out / "normals.npy")
    enhanced = np.load(out / "normals_enhanced.npy")
    assert enhanced.shape == normals.shape and enhanced.dtype == np.float32
    assert np.all(enhanced[~mask] == 0.0)
    error = _mean_error(normals, truth, mask)  # the unenhanced normals
    print(f"\ncolour sphere: mean angular error {error:.4f} deg")
    assert error < SPHERE_MAX_MEAN_DEG
    assert _mean_error(enhanced, normals, mask) > 0.01  # the enhanced ones differ
    picture = cv2.cvtColor(cv2.imread(str(out / "normal_map.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(picture, normal_map_rgb(enhanced, mask=mask))

    report = json.loads((out / "report.json").read_text())
    assert report["bit_depth"] == 16
    assert report["colour_conversion"].startswith("colour: each channel divided by its")
    assert report["enhancement"] == {"w": 5, "k": 2.5}
    assert report["depth_unit"] == "m" and report["pixel_size"] == 1e-4
    depth = np.load(out / "depth.npy")
    span = (height.max() - height[mask].min()) * 1e-4  # a 5 mm sphere at 0.1 mm a pixel
    assert np.nanmax(depth) - np.nanmin(depth) == pytest.approx(span, rel=0.05)
    assert "angular error vs Normal_gt.mat" in run.stdout


def test_the_channel_intensities_matter(offline_recon: Callable, tmp_path: Path) -> None:
    # Without light_intensities.txt the colour sphere is visibly wrong: the rule is used.
    truth, mask, _ = _write_sphere(tmp_path / "sphere", colour16=True)
    (tmp_path / "sphere/light_intensities.txt").unlink()
    _ok(offline_recon(tmp_path / "sphere", "--out", tmp_path / "out"))
    assert _mean_error(np.load(tmp_path / "out/normals.npy"), truth, mask) > 1.0


@pytest.mark.parametrize("model", ["lambert", "hk"])
def test_96_lights_as_every_diligent_object(offline_recon: Callable, tmp_path: Path,
                                            model: str) -> None:
    # Real DiLiGenT objects have 96 lights (more than the 62 once supported): a 16-bit colour
    # sphere under 96 lights, reconstructed with either model.
    truth, mask, _ = _write_sphere(tmp_path / "sphere", colour16=True, count=96)
    out = tmp_path / "out"
    run = _ok(offline_recon(tmp_path / "sphere", "--out", out, "--model", model))
    normals = np.load(out / "normals.npy")
    valid = np.linalg.norm(normals, axis=2) > 0
    assert valid.sum() == mask.sum() and not np.any(valid & ~mask)
    error = _mean_error(normals, truth, mask)
    print(f"\n96-light sphere, {model}: mean angular error {error:.4f} deg")
    assert error < SPHERE_96_MAX_MEAN_DEG
    report = json.loads((out / "report.json").read_text())
    assert (report["images"], report["model"]) == (96, model)
    assert report["normal_gt"]["mean_deg"] == pytest.approx(error, abs=1e-4)
    assert "offline_recon: 96 images 140x120 16-bit" in run.stdout


# ----------------------------------------------------------------------------- rig finger


@pytest.fixture(scope="module")
def finger_folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SimulatedRig]:
    folder = tmp_path_factory.mktemp("finger")
    rig = SimulatedRig()
    names = []
    for k in range(rig.led_count):
        frame = np.clip(np.rint(rig.noiseless(Scene.FINGER, [k]) * 255), 0, 255)
        names.append(f"led{k}.png")
        assert cv2.imwrite(str(folder / names[-1]), frame.astype(np.uint8))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", rig.light_directions_ps())
    np.savetxt(folder / "light_intensities.txt", rig.light_intensities())
    truth = rig.finger_truth()
    scipy.io.savemat(folder / "Normal_gt.mat",
                     {"Normal_gt": np.where(truth.mask[..., None], truth.normals_ps, 0.0)})
    return folder, rig


def test_rig_finger_without_mask(offline_recon: Callable, tmp_path: Path,
                                 finger_folder: tuple[Path, SimulatedRig]) -> None:
    folder, rig = finger_folder
    truth = rig.finger_truth()
    out = tmp_path / "out"
    run = _ok(offline_recon(folder, "--out", out, "--pixel-size", "3e-5"))
    assert "no mask.png: the pipeline's finger mask" in run.stdout
    normals = np.load(out / "normals.npy")
    assert normals.shape == (rig.camera.height, rig.camera.width, 3)
    valid = np.linalg.norm(normals, axis=2) > 0
    assert (valid & truth.mask).sum() > 0.95 * truth.mask.sum()
    assert (valid & ~truth.mask).sum() < 0.01 * truth.mask.sum()
    error = _mean_error(normals, truth.normals_ps, valid & truth.mask)
    print(f"\nrig finger: mean angular error {error:.3f} deg")
    assert error < FINGER_MAX_MEAN_DEG
    report = json.loads((out / "report.json").read_text())
    assert report["mask_source"] == "pipeline finger mask" and report["mask_pixels"] is None
    assert report["normal_gt"]["mean_deg"] == pytest.approx(error, abs=0.05)

    # Heights in metres at 30 um a pixel against the truth (perspective, so not exact).
    depth = np.load(out / "depth.npy")
    both = valid & truth.mask
    true_height = -truth.depth_m.astype(np.float64)
    true_height -= true_height[both].mean()
    ours = depth - depth[both].mean()
    span = np.ptp(true_height[both])
    assert np.ptp(ours[both]) == pytest.approx(span, rel=0.05)  # measured 5.12 vs 5.21 mm
    assert np.sqrt(np.mean((ours[both] - true_height[both]) ** 2)) < 2e-4  # measured 82 um

    # The 500 ppi rolled print, its resolution in the PNG's pHYs chunk (read byte by byte).
    assert report["fingerprint"]["made"] and "fingerprint.png" in report["outputs"]
    data = (out / "fingerprint.png").read_bytes()
    chunks, at = {}, 8
    while at < len(data):
        length, kind = struct.unpack(">I4s", data[at:at + 8])
        chunks.setdefault(kind, data[at + 8:at + 8 + length])
        at += 12 + length
    assert list(chunks)[:2] == [b"IHDR", b"pHYs"]
    assert struct.unpack(">IIB", chunks[b"pHYs"]) == (19685, 19685, 1)  # 500 ppi, metres
    print_image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert print_image.ndim == 2 and print_image.dtype == np.uint8
    width_mm = print_image.shape[1] / 19.685
    assert 10 < width_mm < 25, width_mm  # the rig's finger is ~15 mm across, ~18 mm rolled
    assert "fingerprint.png: " in run.stdout

    # The same print as a WSQ file beside it, decoded by NBIS: 500 ppi, the PNG's pixels.
    records = report["fingerprint"]["records"]
    assert records["fingerprint.wsq"]["made"] and "fingerprint.wsq" in report["outputs"]
    wsq_data = (out / "fingerprint.wsq").read_bytes()
    wsq_image, ppi = decode_wsq(wsq_data)
    assert ppi == 500 and wsq_image.shape == print_image.shape
    assert np.sqrt(np.mean((wsq_image.astype(np.float64) - print_image) ** 2)) < MAX_RMS_ERROR
    assert "fingerprint.wsq: " in run.stdout
    # Its minutiae record and its ANSI/NIST transaction, read back from the standards' layouts
    # (tests/record_readers.py): the same print, the same WSQ file, the same minutiae.
    # NFIQ 2 cannot score this small print (352 x 300 px): the report says so, the rest is made.
    assert records["nfiq2"] is None and "NFIQ 2" in records["nfiq2_problem"]
    assert records["minutiae"] > 0
    iso = read_iso_19794_2_2005((out / "fingerprint.fmr").read_bytes())
    assert (iso["width"], iso["height"]) == (print_image.shape[1], print_image.shape[0])
    assert len(iso["minutiae"]) == records["minutiae"] and iso["quality"] == 0
    transaction = read_ansi_nist((out / "fingerprint.an2").read_bytes())
    assert [t for t, _ in transaction] == [1, 14, 9]
    assert transaction[1][1][999] == wsq_data
    assert len(transaction[2][1][137]) == records["minutiae"]
    assert [(m["x"], m["y"]) for m in iso["minutiae"]] == [
        (int(row[1]), int(row[2])) for row in transaction[2][1][137]]
    assert scalar(transaction[0][1], 9) == out.name  # TCN: the output folder's name
    for name in ("fingerprint.fmr", "fingerprint.an2"):
        assert name in report["outputs"] and f"{name}: " in run.stdout


def test_model_hk(offline_recon: Callable, tmp_path: Path,
                  finger_folder: tuple[Path, SimulatedRig]) -> None:
    folder, _ = finger_folder
    run = offline_recon(folder, "--out", tmp_path / "out", "--model", "hk")
    if importlib.util.find_spec("fingerps_recon.photometric.hk_solver") is None:
        assert run.returncode == 2
        assert run.stderr.strip() == ("offline_recon: error: the HK solver is not available "
                                      "in this build; use --model lambert")
        assert not (tmp_path / "out").exists()
    else:
        _ok(run)
        assert json.loads((tmp_path / "out/report.json").read_text())["model"] == "hk"


# ----------------------------------------------------------------------------- bad input


def _small_sphere(folder: Path) -> None:
    _write_sphere(folder, colour16=False, size=(40, 48), radius=16.0, count=6)


def _arguments(folder: Path, case: str) -> list[str]:
    """Spoil a valid small-sphere folder (`diligent_cases`) or the command line in one way;
    returns the extra arguments."""
    if case in CASES:
        spoil_folder(folder, case)
    elif case == "missing folder":
        return ["--out", str(folder.parent / "out"), str(folder.parent / "nowhere")]
    elif case == "out is a file":
        (folder.parent / "file").write_text("")
        return ["--out", str(folder.parent / "file")]
    elif case == "saturation above full scale":
        return ["--saturation", "300"]
    elif case == "even --w":
        return ["--w", "4"]
    else:
        raise AssertionError(case)
    return []


BAD_CASES = {
    "missing folder": "nowhere: no such folder",
    "filenames.txt missing": "filenames.txt: missing",
    "listed image missing": "003.png is listed in filenames.txt but",
    "image sizes differ": "003.png is 49x40 but 001.png is 48x40",
    "light rows != images": "light_directions.txt has 5 rows but filenames.txt lists 6 images",
    "light row of 2 numbers": "light_directions.txt line 6: 2 numbers, expected 3",
    "zero light row": "light_directions.txt row 6 is a zero vector",
    "non-unit light row": "light_directions.txt row 6 has length 0.5, not a unit vector",
    "mask size": "mask.png is 48x41 but the images are 48x40",
    "mask selects nothing": "mask.png selects nothing",
    "all-dark image": "002.png is dark",
    "out is a file": "exists and is not a folder",
    "saturation above full scale": "at most at the 8-bit full scale 255, got 300",
    "even --w": "argument --w: 4 must be an odd integer >= 3",
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_exits_2_with_one_line(offline_recon: Callable, tmp_path: Path,
                                         case: str) -> None:
    folder = tmp_path / "sphere"
    _small_sphere(folder)
    extra = _arguments(folder, case)
    args = extra if case == "missing folder" else [folder, "--out", tmp_path / "out", *extra]
    run = offline_recon(*args)
    assert run.returncode == 2, f"{run.stdout}\n{run.stderr}"
    assert "Traceback" not in run.stderr and run.stdout == ""
    message = run.stderr.strip().splitlines()[-1]
    assert BAD_CASES[case] in message, run.stderr
    if not case.startswith("even"):  # argparse prints its usage line first
        assert len(run.stderr.strip().splitlines()) == 1
        assert message.startswith("offline_recon: error: ")


def test_the_small_sphere_itself_is_fine(offline_recon: Callable, tmp_path: Path) -> None:
    # The bad-input cases above differ from this valid folder in one way each.
    _small_sphere(tmp_path / "sphere")
    _ok(offline_recon(tmp_path / "sphere", "--out", tmp_path / "out"))


def test_help_names_the_colour_rule(offline_recon: Callable) -> None:
    run = _ok(offline_recon("--help"))
    text = " ".join(run.stdout.split())
    assert "each channel is divided by its intensity and the channels are averaged" in text
    assert "Rec. 601 luma" in text and "--pixel-size" in text and "--model" in text
