"""Round-trip and parser tests of fingerps_recon.surface.ply."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.surface.ply import read_ply, write_ply


def _cloud(n: int = 257) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    points = rng.normal(scale=0.01, size=(n, 3)) + np.array([0, 0, 0.05])
    intensity = rng.uniform(0, 4095, size=n)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, intensity, normals


def test_round_trip_points_only(tmp_path: Path) -> None:
    points, _, _ = _cloud()
    path = tmp_path / "cloud.ply"
    write_ply(path, points)
    data = read_ply(path)
    assert set(data) == {"points"}
    assert data["points"].dtype == np.float32 and data["points"].shape == points.shape
    np.testing.assert_array_equal(data["points"], points.astype(np.float32))


def test_round_trip_with_intensity_and_normals(tmp_path: Path) -> None:
    points, intensity, normals = _cloud()
    path = tmp_path / "cloud.ply"
    write_ply(str(path), points, intensity=intensity, normals=normals)
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n") + len(b"end_header\n")].decode("ascii")
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")
    assert "element vertex 257\n" in header
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert props == ["x", "y", "z", "intensity", "nx", "ny", "nz"]
    assert len(raw) == len(header) + 257 * 7 * 4
    data = read_ply(path)
    np.testing.assert_array_equal(data["points"], points.astype(np.float32))
    np.testing.assert_array_equal(data["intensity"], intensity.astype(np.float32))
    np.testing.assert_array_equal(data["normals"], normals.astype(np.float32))


def test_empty_cloud_and_file_objects() -> None:
    buf = io.BytesIO()
    write_ply(buf, np.zeros((0, 3)), intensity=np.zeros(0))
    buf.seek(0)
    data = read_ply(buf)
    assert data["points"].shape == (0, 3) and data["intensity"].shape == (0,)


def test_reads_ascii_with_faces_before_vertices() -> None:
    text = (
        "ply\nformat ascii 1.0\ncomment made by hand\n"
        "element face 1\nproperty list uchar int vertex_indices\n"
        "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nend_header\n"
        "3 0 1 2\n"
        "0 0 0 255\n1 0 0 128\n0 1.5 0 0\n"
    )
    data = read_ply(io.BytesIO(text.encode("ascii")))
    np.testing.assert_array_equal(data["points"], [[0, 0, 0], [1, 0, 0], [0, 1.5, 0]])
    assert data["red"].dtype == np.uint8
    np.testing.assert_array_equal(data["red"], [255, 128, 0])


def test_reads_big_endian_binary_with_list_element() -> None:
    vertex = np.array(
        [(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)], dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8")]
    )
    faces = np.array([3], ">u1").tobytes() + np.array([0, 1, 1], ">i4").tobytes()
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
        "property double y\nproperty double z\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    data = read_ply(io.BytesIO(header.encode("ascii") + vertex.tobytes() + faces))
    assert data["points"].dtype == np.float64
    np.testing.assert_array_equal(data["points"], [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "content",
    [
        b"PLY\nformat ascii 1.0\nend_header\n",
        b"ply\nformat binary_little_endian 2.0\nend_header\n",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n0\n",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n\x00\x00"
        ),
    ],
)
def test_bad_files_raise(content: bytes) -> None:
    with pytest.raises(FingerpsReconError):
        read_ply(io.BytesIO(content))


def test_bad_arrays_raise(tmp_path: Path) -> None:
    points, intensity, normals = _cloud(5)
    with pytest.raises(FingerpsReconError, match="points"):
        write_ply(tmp_path / "a.ply", points[:, :2])
    with pytest.raises(FingerpsReconError, match="intensity"):
        write_ply(tmp_path / "a.ply", points, intensity=intensity[:4])
    with pytest.raises(FingerpsReconError, match="normals"):
        write_ply(tmp_path / "a.ply", points, normals=normals.T)
