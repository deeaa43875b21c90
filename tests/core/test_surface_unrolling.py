"""Tests of fingerps_recon.surface.surface_unrolling on analytic surfaces seen through a pinhole.

A cylinder (radius 8 mm, axis vertical in the image, a finger's width) is developable: the
unrolling must keep every distance along the surface. A sphere cap (radius 10 mm, out to a
65 deg slope, like the rig's finger) is not: the springs model spreads the unavoidable
strain, and the bounds below document how much.

Measured (rig camera, 0.5 mm mesh): cylinder, dot pairs >= 2 mm apart on a 1 mm lattice
out to 57 deg: max relative distance error 1.75 %, rms 0.23 % (0.24 % at most among dots
within 43 deg: the error is at the steep sides, where the per-pixel map interpolates
linearly between nodes 1.2 mm apart on the skin); spring strain ~1e-10; 50 um ridges move
the layout by 1.3 um. Sphere cap: rms strain 3.6 %, max 16 % (at the rim); dot pairs
(rings every 10 deg out to 60 deg, as far as the image shows them): median |error| 2.5 %,
max 20 % (along the 60 deg ring, where the image cuts the cap: the layout stretches it as
an azimuthal equidistant map would, 1.047 / sin 60 deg = +21 %), max 6.5 % among the dots
within 40 deg; geodesic radii from the apex shorter by 3.1 % (median).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from fingerps_recon.errors import FingerpsReconError, UnrollingError
from fingerps_recon.surface.surface_unrolling import unroll_surface

SHAPE = (493, 659)
K = np.array([[3000.0, 0.0, (SHAPE[1] - 1) / 2], [0.0, 3000.0, (SHAPE[0] - 1) / 2],
              [0.0, 0.0, 1.0]])
APEX_MM = 90.0
MAX_SLOPE_DEG = 65.0
#: Cylinder: largest relative error of a distance >= 2 mm along the surface.
CYLINDER_MAX_ERROR = 0.02
#: Sphere cap (not developable): median and largest relative distance error, rms strain.
SPHERE_MEDIAN_ERROR = 0.04
SPHERE_MAX_ERROR = 0.25
#: ... among the dots within 40 deg of the apex (the pad of a finger).
SPHERE_INNER_MAX_ERROR = 0.08
SPHERE_STRAIN_RMS = (0.01, 0.05)


def _rays() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def _project(points_mm: np.ndarray) -> np.ndarray:
    """(N, 2) pixel (col, row) of optical-frame points (N, 3)."""
    return points_mm[:, :2] / points_mm[:, 2:] * K[0, 0] + K[:2, 2]


def cylinder(radius: float = 8.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth (m), mask and arc-length coordinates (s, Y) (mm) of a vertical cylinder whose
    nearest line is at APEX_MM; s = radius * angle from that line, positive to the right."""
    xn, yn = _rays()
    zc = APEX_MM + radius
    a = 1 + xn**2
    disc = zc**2 - a * (zc**2 - radius**2)
    t = (zc - np.sqrt(np.maximum(disc, 0.0))) / a
    angle = np.arctan2(t * xn, zc - t)
    mask = (disc > 0) & (np.abs(angle) <= np.radians(MAX_SLOPE_DEG))
    return np.where(mask, t / 1e3, np.nan), mask, np.stack([radius * angle, t * yn], -1)


def cylinder_point(s: np.ndarray, y: np.ndarray, radius: float = 8.0) -> np.ndarray:
    angle = s / radius
    return np.stack([radius * np.sin(angle), y,
                     APEX_MM + radius * (1 - np.cos(angle))], -1)


def sphere(radius: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and mask of a sphere cap (apex at APEX_MM on the axis, out to MAX_SLOPE)."""
    xn, yn = _rays()
    zc = APEX_MM + radius
    a = 1 + xn**2 + yn**2
    disc = zc**2 - a * (zc**2 - radius**2)
    t = (zc - np.sqrt(np.maximum(disc, 0.0))) / a
    polar = np.arccos(np.clip((zc - t) / radius, -1, 1))
    mask = (disc > 0) & (polar <= np.radians(MAX_SLOPE_DEG))
    return np.where(mask, t / 1e3, np.nan), mask


def sphere_point(polar: np.ndarray, azimuth: np.ndarray, radius: float = 10.0) -> np.ndarray:
    return np.stack([radius * np.sin(polar) * np.cos(azimuth),
                     radius * np.sin(polar) * np.sin(azimuth),
                     APEX_MM + radius * (1 - np.cos(polar))], -1)


def _forward(unrolling, pixels: np.ndarray) -> np.ndarray:
    """Unrolled (x, y) at sub-pixel positions (bilinear in the per-pixel map)."""
    coords = [pixels[:, 1], pixels[:, 0]]
    return np.stack([scipy.ndimage.map_coordinates(unrolling.pixel_xy_mm[..., c], coords,
                                                   order=1, mode="nearest")
                     for c in range(2)], -1)


def _pair_errors(xy: np.ndarray, geodesic: np.ndarray, min_mm: float = 2.0) -> np.ndarray:
    i, j = np.triu_indices(len(xy), 1)
    d2 = np.linalg.norm(xy[i] - xy[j], axis=1)
    keep = geodesic[i, j] >= min_mm
    return d2[keep] / geodesic[i, j][keep] - 1.0


@pytest.fixture(scope="module")
def cylinder_case():
    depth, mask, arc = cylinder()
    return depth, mask, arc, unroll_surface(depth, mask=mask, camera_matrix=K)


@pytest.fixture(scope="module")
def sphere_case():
    depth, mask = sphere()
    return depth, mask, unroll_surface(depth, mask=mask, camera_matrix=K)


def test_cylinder_keeps_distances_along_the_surface(cylinder_case) -> None:
    _, _, _, unrolling = cylinder_case
    # Dots on a 1 mm lattice in arc length, out to 57 deg around (s = 8 mm).
    s, y = np.meshgrid(np.arange(-8.0, 8.5, 1.0), np.arange(-6.0, 6.5, 1.0))
    s, y = s.ravel(), y.ravel()
    xy = _forward(unrolling, _project(cylinder_point(s, y)))
    assert np.isfinite(xy).all()
    geodesic = np.hypot(s[:, None] - s[None, :], y[:, None] - y[None, :])
    err = _pair_errors(xy, geodesic)
    print(f"\ncylinder: {len(err)} pairs, max |error| {100 * np.abs(err).max():.2f} %, "
          f"rms {100 * np.sqrt(np.mean(err**2)):.3f} %, strain rms {unrolling.strain_rms:.2e}")
    assert np.abs(err).max() <= CYLINDER_MAX_ERROR
    assert unrolling.strain_rms < 1e-3


def test_cylinder_is_not_mirrored_nor_turned(cylinder_case) -> None:
    _, mask, arc, unrolling = cylinder_case
    xy = unrolling.pixel_xy_mm[mask]
    truth = arc[mask]
    a = xy - xy.mean(axis=0)
    b = truth - truth.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    rotation = u @ vt
    assert np.linalg.det(rotation) > 0  # a mirror image would need a reflection
    angle = np.degrees(np.arctan2(rotation[1, 0], rotation[0, 0]))
    print(f"\ncylinder: rotation to the truth {angle:.3f} deg")
    assert abs(angle) < 0.5
    # x right, y down: the image's right is the print's right, the image's top its top.
    assert np.corrcoef(xy[:, 0], truth[:, 0])[0, 1] > 0.999
    assert np.corrcoef(xy[:, 1], truth[:, 1])[0, 1] > 0.999


def test_inverse_map_returns_the_source_pixels(cylinder_case) -> None:
    _, _, _, unrolling = cylinder_case
    s, y = np.meshgrid(np.arange(-6.0, 6.5, 2.0), np.arange(-5.0, 5.5, 2.0))
    pixels = _project(cylinder_point(s.ravel(), y.ravel()))
    xy = _forward(unrolling, pixels)
    # A regular grid whose points include each dot's unrolled position: one column and
    # one row per dot, evaluated exactly (coarse_step=1).
    for (x0, y0), (col, row) in zip(xy, pixels, strict=True):
        map_x, map_y = unrolling.source_pixels(np.array([x0, x0 + 0.05]),
                                               np.array([y0, y0 + 0.05]), coarse_step=1)
        assert abs(map_x[0, 0] - col) < 0.5 and abs(map_y[0, 0] - row) < 0.5


def test_sphere_cap_strain_is_bounded(sphere_case) -> None:
    _, _, unrolling = sphere_case
    rings, spokes = np.meshgrid(np.radians(np.arange(10, 61, 10)),
                                np.radians(np.arange(0, 360, 30)))
    polar = np.concatenate([[0.0], rings.ravel()])  # the apex, then 6 rings of 12 dots
    azimuth = np.concatenate([[0.0], spokes.ravel()])
    points = sphere_point(polar, azimuth)
    pixels = _project(points)
    seen = ((pixels >= 0) & (pixels <= np.array(SHAPE[::-1]) - 1)).all(axis=1)
    polar, points, pixels = polar[seen], points[seen], pixels[seen]  # the image cuts rings
    assert len(points) > 50
    xy = _forward(unrolling, pixels)
    assert np.isfinite(xy).all()
    unit = (points - [0, 0, APEX_MM + 10.0]) / 10.0
    geodesic = 10.0 * np.arccos(np.clip(unit @ unit.T, -1, 1))
    err = _pair_errors(xy, geodesic)
    inner = polar <= np.radians(40.0)
    err_inner = _pair_errors(xy[inner], geodesic[np.ix_(inner, inner)])
    radial = np.linalg.norm(xy - xy[0], axis=1)[1:] / (10.0 * polar[1:]) - 1
    print(f"\nsphere cap: strain rms {100 * unrolling.strain_rms:.2f} %, max "
          f"{100 * unrolling.strain_max:.1f} %; pairs: median |error| "
          f"{100 * np.median(np.abs(err)):.2f} %, max {100 * np.abs(err).max():.2f} % (within "
          f"40 deg: {100 * np.abs(err_inner).max():.2f} %); radii {100 * np.median(radial):+.2f} %")
    assert np.abs(err_inner).max() <= SPHERE_INNER_MAX_ERROR
    assert np.median(np.abs(err)) <= SPHERE_MEDIAN_ERROR
    assert np.abs(err).max() <= SPHERE_MAX_ERROR
    assert SPHERE_STRAIN_RMS[0] < unrolling.strain_rms < SPHERE_STRAIN_RMS[1]
    # The apex (the point nearest the camera) is the origin, within a mesh spacing.
    assert np.linalg.norm(xy[0]) < 0.4


def test_ridges_do_not_enter_the_geometry(cylinder_case) -> None:
    depth, mask, arc, plain = cylinder_case
    # 50 um peak-to-valley ridges, period 0.5 mm, oblique, along the normal ~ along z here.
    ridges = 25e-6 * np.cos(2 * np.pi * (arc[..., 0] + 0.5 * arc[..., 1]) / 0.5)
    rough = unroll_surface(depth - ridges, mask=mask, camera_matrix=K)
    # The cylinder's nearest points are a line: the ridges may pick another apex on it.
    moved = rough.pixel_xy_mm[mask] - plain.pixel_xy_mm[mask]
    shift = np.abs(moved - moved.mean(axis=0)).max()
    print(f"\nridges: strain rms {rough.strain_rms:.2e}, largest shift {shift * 1e3:.1f} um")
    assert rough.strain_rms < 2e-3
    assert shift < 0.03
    # Without smoothing at the mesh scale they would (the test can fail).
    raw = unroll_surface(depth - ridges, mask=mask, camera_matrix=K, smoothing_nodes=0.0)
    assert raw.strain_rms > 2 * rough.strain_rms


def test_per_pixel_map_covers_the_mask(cylinder_case) -> None:
    _, mask, _, unrolling = cylinder_case
    xy = unrolling.pixel_xy_mm
    assert xy.shape == (*SHAPE, 2) and xy.dtype == np.float32
    assert np.isfinite(xy[mask]).all()
    assert np.isnan(xy[~mask]).all()
    assert unrolling.node_xy_mm.shape == (unrolling.node_pixel.shape[0], 2)
    assert unrolling.iterations <= 10


@pytest.mark.parametrize("case", ["empty", "tiny", "shape", "nan"])
def test_bad_input(case: str) -> None:
    depth, mask, _ = cylinder()
    if case == "empty":
        mask = np.zeros_like(mask)
    elif case == "tiny":
        mask = np.zeros_like(mask)
        mask[240:250, 320:330] = True
    elif case == "shape":
        mask = mask[:-1]
    else:
        depth = np.full_like(depth, np.nan)
    with pytest.raises(UnrollingError):
        unroll_surface(depth, mask=mask, camera_matrix=K)


def test_bad_camera_matrix() -> None:
    depth, mask, _ = cylinder()
    with pytest.raises(FingerpsReconError):
        unroll_surface(depth, mask=mask, camera_matrix=np.eye(2))
