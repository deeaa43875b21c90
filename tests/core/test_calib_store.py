"""Tests of fingerps_calib.calibration_store: the saved calibration, round trips and failures."""

from __future__ import annotations

import os

import numpy as np
import pytest
import yaml

from fingerps_calib import calibration_store
from fingerps_calib.calibration_store import (
    FlatFieldRecord,
    LightsRecord,
    load_flat_field,
    load_lights,
    save_flat_field,
    save_lights,
)
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.led_triangulation import Placement, combine_placements

K = np.array([[3000.0, 0.0, 329.0], [0.0, 3000.0, 246.0], [0.0, 0.0, 1.0]])
LEDS = np.array([[0.040, 0.005, 0.001], [-0.020, 0.035, -0.002], [-0.030, -0.028, 0.0015]])
STAMP = 1_760_000_000_123_456_789


def _placement(centre: tuple[float, float, float]) -> Placement:
    c = np.asarray(centre)
    origins = c + 0.004 * np.array([[0.1, 0.0, -1.0], [0.0, 0.1, -1.0], [-0.1, 0.0, -1.0]])
    directions = LEDS - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return Placement(c, 0.004, 0.1, origins, directions, np.array([[300.5, 200.25]] * 3),
                     np.array([0.05, 0.02, 0.04]))


def _record(placements: list[Placement]) -> LightsRecord:
    lights = combine_placements(placements,
                                reference_point_optical_m=np.array([0.0, 0.0025, 0.09]))
    assert lights.ok, lights.problems
    return LightsRecord(camera_name="fingerps_sim", frame_id="fingerps_camera_optical_frame",
                        stamp_ns=STAMP, image_width=659, image_height=493, camera_matrix=K,
                        lights=lights)


def _flat(seed: int = 0) -> FlatFieldRecord:
    rng = np.random.default_rng(seed)
    portions = rng.uniform(0.3, 1.0, (3, 40, 50)).astype(np.float32)
    return FlatFieldRecord(camera_name="fingerps_sim", frame_id="cam", stamp_ns=STAMP + seed,
                           portions=portions, relative_intensities=np.array([1.0, 0.9, 0.8]),
                           fit_residuals=np.array([0.005, 0.004, 0.006]), polynomial_degree=4)


@pytest.mark.parametrize("count", [1, 2])
def test_lights_round_trip_is_exact(tmp_path, count):
    record = _record([_placement((0.002, -0.0015, 0.094)),
                      _placement((-0.005, 0.002, 0.094))][:count])
    path = save_lights(tmp_path, record)
    assert path == tmp_path / "lights.yaml"
    loaded = load_lights(tmp_path)
    assert (loaded.camera_name, loaded.frame_id, loaded.stamp_ns, loaded.image_width,
            loaded.image_height) == ("fingerps_sim", "fingerps_camera_optical_frame", STAMP,
                                     659, 493)
    np.testing.assert_array_equal(loaded.camera_matrix, K)
    a, b = record.lights, loaded.lights
    np.testing.assert_array_equal(b.directions_optical, a.directions_optical)
    np.testing.assert_array_equal(b.residuals_px, a.residuals_px)
    np.testing.assert_array_equal(b.sphere_center_optical_m, a.sphere_center_optical_m)
    assert b.edge_rms_px == a.edge_rms_px and len(b.placements) == count
    for pa, pb in zip(a.placements, b.placements, strict=True):
        for name in ("sphere_center_optical_m", "highlight_points_optical_m",
                     "directions_optical", "highlights_uv", "residuals_px"):
            np.testing.assert_array_equal(getattr(pb, name), getattr(pa, name))
    if count == 1:
        assert b.triangulation is None and b.led_positions_optical_m.shape == (0, 3)
    else:
        np.testing.assert_allclose(b.led_positions_optical_m, LEDS, atol=1e-9)
        for name in ("led_positions_optical_m", "reference_point_optical_m",
                     "ray_angles_deg", "direction_residuals_deg"):
            np.testing.assert_array_equal(getattr(b.triangulation, name),
                                          getattr(a.triangulation, name))


def test_the_lights_file_is_readable_and_names_camera_date_and_residuals(tmp_path):
    save_lights(tmp_path, _record([_placement((0.002, -0.0015, 0.094)),
                                   _placement((-0.005, 0.002, 0.094))]))
    text = (tmp_path / "lights.yaml").read_text()
    assert text.startswith("# fingerps light calibration")
    doc = yaml.safe_load(text)
    assert doc["camera_name"] == "fingerps_sim"
    assert doc["date"] == "2025-10-09T08:53:20Z"
    assert doc["method"].startswith("2 placements")
    assert set(doc["fit"]) == {"edge_rms_px_max", "highlight_residual_px_max",
                               "led_position_residual_mm_max", "direction_residual_deg_max"}
    led = doc["leds"][0]
    assert {"direction", "direction_ps", "highlight_residual_px", "position_m",
            "position_residual_mm"} <= led.keys()
    np.testing.assert_allclose(led["direction_ps"][1:], [-x for x in led["direction"][1:]])
    assert "direction: [" in text  # vectors on one line


def test_flat_field_round_trip_and_stale_maps_removed(tmp_path):
    first = save_flat_field(tmp_path, _flat(0))
    second = save_flat_field(tmp_path, _flat(1))
    assert first == second == tmp_path / "flat_field.yaml"
    maps = sorted(p.name for p in tmp_path.glob("flat_field_*.npz"))
    assert len(maps) == 1 and maps[0] == yaml.safe_load(second.read_text())["maps_file"]
    loaded = load_flat_field(tmp_path)
    expected = _flat(1)
    np.testing.assert_array_equal(loaded.portions, expected.portions)
    assert loaded.portions.dtype == np.float32
    np.testing.assert_array_equal(loaded.relative_intensities, expected.relative_intensities)
    np.testing.assert_allclose(loaded.fit_residuals, expected.fit_residuals, rtol=1e-12)
    assert (loaded.camera_name, loaded.stamp_ns, loaded.polynomial_degree) == \
        ("fingerps_sim", STAMP + 1, 4)


def test_nothing_saved_loads_as_none(tmp_path):
    assert load_lights(tmp_path) is None
    assert load_flat_field(tmp_path) is None
    assert load_lights(tmp_path / "missing") is None


def test_damaged_files_are_refused_with_what_to_do(tmp_path):
    (tmp_path / "lights.yaml").write_text("format: fingerps_light_calibration/1\nleds: [\n")
    with pytest.raises(FingerpsCalibError, match=r"not valid YAML.*recalibrate"):
        load_lights(tmp_path)
    (tmp_path / "lights.yaml").write_text("format: something_else\n")
    with pytest.raises(FingerpsCalibError, match="not a fingerps_light_calibration/1 file"):
        load_lights(tmp_path)
    (tmp_path / "lights.yaml").write_text("format: fingerps_light_calibration/1\n")
    with pytest.raises(FingerpsCalibError, match=r"not a complete light calibration.*KeyError"):
        load_lights(tmp_path)
    save_flat_field(tmp_path, _flat())
    maps = next(tmp_path.glob("flat_field_*.npz"))
    maps.write_bytes(maps.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(FingerpsCalibError, match=r"SHA-256.*changed or damaged"):
        load_flat_field(tmp_path)
    maps.unlink()
    with pytest.raises(FingerpsCalibError, match="maps file that is missing"):
        load_flat_field(tmp_path)


def test_a_failed_write_leaves_the_old_calibration(tmp_path, monkeypatch):
    record = _record([_placement((0.002, -0.0015, 0.094))])
    save_lights(tmp_path, record)
    before = (tmp_path / "lights.yaml").read_bytes()

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(calibration_store.os, "replace", full_disk)
    later = LightsRecord("fingerps_sim", "f", STAMP + 10**9, 659, 493, K, record.lights)
    with pytest.raises(FingerpsCalibError, match=r"No space left.*previous calibration is "
                                                  r"unchanged"):
        save_lights(tmp_path, later)
    with pytest.raises(FingerpsCalibError):
        save_flat_field(tmp_path, _flat())
    monkeypatch.undo()
    assert (tmp_path / "lights.yaml").read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["lights.yaml"]  # no temporary file left
    assert load_flat_field(tmp_path) is None


def test_an_unwritable_directory_is_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(FingerpsCalibError, match="cannot create the calibration directory"):
        save_lights(blocker / "calibration", _record([_placement((0.002, -0.0015, 0.094))]))
