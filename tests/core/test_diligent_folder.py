"""Reading DiLiGenT-layout folders (`fingerps_recon.offline.diligent_folder`) written in tmp_path.

Small synthetic folders with known pixel values: the grey conversion rules (the inverse-
intensity mean for three-channel intensities, Rec. 601 luma otherwise), the RGB channel order
(OpenCV reads BGR), saturation marking, the light rows, the optional files, and one refusal per
kind of bad input, each with a message that names the problem.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from diligent_cases import CASES, spoil_folder

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.offline.diligent_folder import (
    LUMA_601,
    ColourConversion,
    default_shadow_level,
    load_diligent_folder,
)

H, W = 6, 8
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])


def _write(folder: Path, images: list[np.ndarray], *, lights: np.ndarray = LIGHTS,
           intensities: np.ndarray | None = None, mask: np.ndarray | None = None) -> Path:
    """A DiLiGenT-layout folder; colour images are given as RGB."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, img in enumerate(images):
        names.append(f"img/{i:03d}.png")
        (folder / "img").mkdir(exist_ok=True)
        bgr = img[:, :, ::-1] if img.ndim == 3 else img
        assert cv2.imwrite(str(folder / names[-1]), np.ascontiguousarray(bgr))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n\n")
    np.savetxt(folder / "light_directions.txt", lights)
    if intensities is not None:
        np.savetxt(folder / "light_intensities.txt", np.reshape(intensities, (len(images), -1)))
    if mask is not None:
        assert cv2.imwrite(str(folder / "mask.png"), mask.astype(np.uint8) * 255)
    return folder


def _grey8(count: int = 4) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.integers(20, 250, (H, W), dtype=np.uint8) for _ in range(count)]


def _colour16(count: int = 4) -> list[np.ndarray]:
    rng = np.random.default_rng(2)
    return [rng.integers(1000, 60000, (H, W, 3), dtype=np.uint16) for _ in range(count)]


def test_grey_8bit_round_trip(tmp_path: Path) -> None:
    images = _grey8()
    mask = np.zeros((H, W), dtype=bool)
    mask[1:5, 2:7] = True
    data = load_diligent_folder(_write(tmp_path / "f", images, intensities=[1, 2, 3, 4],
                                       mask=mask))
    assert data.images.dtype == np.float32 and data.images.shape == (4, H, W)
    np.testing.assert_array_equal(data.images, np.stack(images).astype(np.float32))
    np.testing.assert_allclose(data.lights_ps, LIGHTS)
    np.testing.assert_array_equal(data.intensities, [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(data.mask, mask)
    assert data.names == ("img/000.png", "img/001.png", "img/002.png", "img/003.png")
    assert data.bit_depth == 8 and data.full_scale == 255.0
    assert data.conversion is ColourConversion.GREY
    assert data.shadow_level == default_shadow_level(8) == pytest.approx(5.1)
    assert data.saturation_level == 255.0
    assert data.normal_gt is None and data.normal_gt_file is None


def test_optional_files_absent(tmp_path: Path) -> None:
    data = load_diligent_folder(_write(tmp_path / "f", _grey8()))
    assert data.intensities is None and data.mask is None and data.normal_gt is None


def test_colour_with_three_channel_intensities_divides_then_averages(tmp_path: Path) -> None:
    images = _colour16()
    e = np.array([[1.0, 2.0, 4.0], [0.5, 0.5, 0.5], [3.0, 1.0, 1.5], [0.8, 1.2, 1.0]])
    data = load_diligent_folder(_write(tmp_path / "f", images, intensities=e))
    assert data.conversion is ColourConversion.INVERSE_INTENSITY and data.bit_depth == 16
    harmonic = 3.0 / (1.0 / e).sum(axis=1)
    np.testing.assert_allclose(data.intensities, harmonic)
    # DiLiGenT's rule: mean over channels of I_c / e_c; times the image's intensity gives
    # the grey value.
    stack = np.stack(images).astype(np.float64)
    expected = (stack / e[:, None, None, :]).mean(axis=3) * harmonic[:, None, None]
    np.testing.assert_allclose(data.images, expected, rtol=1e-6)
    # So grey / intensity is exactly the DiLiGenT-normalised mean.
    np.testing.assert_allclose(data.images / data.intensities[:, None, None],
                               (stack / e[:, None, None, :]).mean(axis=3), rtol=1e-6)


def test_colour_without_intensities_is_rec601_luma_in_rgb_order(tmp_path: Path) -> None:
    images = [np.zeros((H, W, 3), dtype=np.uint8) for _ in range(4)]
    for i, img in enumerate(images):
        img[..., 0] = 200          # R
        img[..., 1] = 20 + 10 * i  # G
        img[..., 2] = 0            # B
    data = load_diligent_folder(_write(tmp_path / "f", images))
    assert data.conversion is ColourConversion.LUMA and data.intensities is None
    for i in range(4):  # BGR order would give 0.299 * 0 + ... + 0.114 * 200
        np.testing.assert_allclose(data.images[i], 0.299 * 200 + 0.587 * (20 + 10 * i),
                                   rtol=1e-6)


def test_colour_with_one_channel_intensities_is_luma(tmp_path: Path) -> None:
    images = _colour16()
    data = load_diligent_folder(_write(tmp_path / "f", images, intensities=[1, 2, 3, 4]))
    assert data.conversion is ColourConversion.LUMA
    np.testing.assert_array_equal(data.intensities, [1, 2, 3, 4])
    np.testing.assert_allclose(data.images, np.stack(images).astype(np.float64) @ LUMA_601,
                               rtol=1e-6)


def test_grey_with_three_channel_intensities_takes_their_luma(tmp_path: Path) -> None:
    e = np.array([[1.0, 2.0, 4.0], [0.5, 0.5, 0.5], [3.0, 1.0, 1.5], [0.8, 1.2, 1.0]])
    data = load_diligent_folder(_write(tmp_path / "f", _grey8(), intensities=e))
    assert data.conversion is ColourConversion.GREY
    np.testing.assert_allclose(data.intensities, e @ LUMA_601)


def test_a_saturated_channel_saturates_the_grey_pixel(tmp_path: Path) -> None:
    images = [np.full((H, W, 3), 30000, dtype=np.uint16) for _ in range(4)]
    images[1][2, 3, 2] = 65535   # one channel clipped
    images[2][4, 5, 0] = 61000   # above a lowered saturation level
    folder = _write(tmp_path / "f", images, intensities=np.ones((4, 3)))
    data = load_diligent_folder(folder)
    assert data.images[1, 2, 3] == 65535.0
    assert data.images[2, 4, 5] < 65535.0
    assert np.count_nonzero(data.images == 65535.0) == 1
    lowered = load_diligent_folder(folder, saturation_level=60000)
    assert lowered.images[2, 4, 5] == 65535.0 and lowered.saturation_level == 60000.0


def test_nearly_unit_light_rows_are_normalised(tmp_path: Path) -> None:
    lights = LIGHTS * np.array([1.01, 0.99, 1.0, 1.015])[:, None]
    data = load_diligent_folder(_write(tmp_path / "f", _grey8(), lights=lights))
    np.testing.assert_allclose(np.linalg.norm(data.lights_ps, axis=1), 1.0)
    np.testing.assert_allclose(data.lights_ps, LIGHTS, atol=1e-12)


@pytest.mark.parametrize("kind", ["mat", "npy"])
def test_ground_truth_normals_are_read(tmp_path: Path, kind: str) -> None:
    folder = _write(tmp_path / "f", _grey8())
    gt = np.zeros((H, W, 3))
    gt[..., 2] = 1.0
    if kind == "mat":
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": gt})
    else:
        np.save(folder / "normal_gt.npy", gt.astype(np.float32))
    data = load_diligent_folder(folder)
    np.testing.assert_array_equal(data.normal_gt, gt)
    assert data.normal_gt_file == ("Normal_gt.mat" if kind == "mat" else "normal_gt.npy")


# ----------------------------------------------------------------------------- refusals


BAD_CASES = {  # every case of diligent_cases, spoiling a valid 4-image grey folder
    "filenames.txt missing": "filenames.txt: missing",
    "listed image missing": "img/002.png is listed in filenames.txt but",
    "image unreadable": "not a readable image",
    "image sizes differ": "img/002.png is 9x6 but img/000.png is 8x6",
    "bit depths differ": "img/002.png is 16-bit but img/000.png is 8-bit",
    "grey and colour": "mix grey and colour",
    "light_directions.txt missing": "light_directions.txt: missing",
    "light rows != images": "light_directions.txt has 3 rows but filenames.txt lists 4 images",
    "malformed light row": "light_directions.txt line 4: '0 x 1' is not a row of numbers",
    "light row of 2 numbers": "light_directions.txt line 4: 2 numbers, expected 3",
    "zero light row": "light_directions.txt row 4 is a zero vector",
    "non-unit light row": "light_directions.txt row 4 has length 0.5, not a unit vector",
    "intensity rows != images": "light_intensities.txt has 5 rows but filenames.txt lists 4 "
                                "images",
    "zero intensity": "light_intensities.txt row 2 is [0.0]: intensities must be > 0",
    "mask size": "mask.png is 8x7 but the images are 8x6",
    "mask selects nothing": "mask.png selects nothing",
    "all-dark image": "img/001.png is dark",
    "too few images": "lists 2 image(s): photometric stereo needs at least 3",
    "Normal_gt.mat shape": "Normal_gt.mat: normals of shape (6, 8)",
    "Normal_gt.mat variable": "has no variable 'Normal_gt'",
}


def test_every_way_of_spoiling_a_folder_is_tried() -> None:
    assert sorted(BAD_CASES) == sorted(CASES)


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_refused_with_a_message(tmp_path: Path, case: str) -> None:
    folder = _write(tmp_path / "f", _grey8())
    spoil_folder(folder, case)
    with pytest.raises(FingerpsReconError) as info:
        load_diligent_folder(folder)
    message = str(info.value)
    assert BAD_CASES[case] in message
    assert "\n" not in message


def test_missing_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(FingerpsReconError, match="no such folder"):
        load_diligent_folder(tmp_path / "nowhere")


@pytest.mark.parametrize(("shadow", "saturation", "fragment"), [
    (-1.0, None, "shadow level must be >= 0"),
    (None, 300.0, "at most at the 8-bit full scale 255"),
    (100.0, 90.0, "above the shadow level 100"),
])
def test_bad_levels_are_refused(tmp_path: Path, shadow: float | None,
                                saturation: float | None, fragment: str) -> None:
    folder = _write(tmp_path / "f", _grey8())
    with pytest.raises(FingerpsReconError, match=fragment):
        load_diligent_folder(folder, shadow_level=shadow, saturation_level=saturation)


def test_inputs_on_disk_are_not_modified(tmp_path: Path) -> None:
    folder = _write(tmp_path / "f", _grey8(), intensities=[1, 2, 3, 4])
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    load_diligent_folder(folder)
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before
