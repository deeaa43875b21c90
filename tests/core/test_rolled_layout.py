"""Tests of fingerps_recon.surface.rolled_layout (``Layout.ROLLED`` of unroll_surface).

The reference is the geometry itself: on the analytic cylinder of test_surface_unrolling the
rolled plane is its arc-length coordinates; on the simulated rig's TRUE surface it is the
skin coordinates the generator defines the finger's print on (``FingerTruth.rolled_mm``:
arc length around the finger along its sections and along it from the apex), in poses with
yaw, pitch and roll.

Measured (this machine, rig finger, TRUE depth, nodes vs the generator's skin coordinates
after a similarity fit, five poses, pitch -6 to +7 deg): residual median 0.004-0.04 mm and
95th percentile 0.02-0.12 mm with the rolled layout (0.003-0.11 and 0.02-0.32 mm without
the pitch's estimate) against 0.15-0.18 / 0.44-0.49 mm with the springs (whose map spreads
the cap's strain over every direction); scale within 0.1 %. Cylinder: the nodes' x equals
their arc length within 0.02 mm. The pitch from an analytic crest (the cap's and the pad's
parabolas, pitched -8 to +8 deg): within 0.1 deg.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_surface_unrolling import K, cylinder

from fingerps_driver.simulation import FingertipShape, RigConfig, SimulatedRig
from fingerps_recon.errors import UnrollingError
from fingerps_recon.surface.rolled_layout import crest_pitch, rolled_layout
from fingerps_recon.surface.surface_unrolling import (
    Layout,
    SurfaceUnrolling,
    cell_triangles,
    unroll_surface,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
from bench_fingerprint import similarity  # the benchmark's fit (Umeyama 1991)

#: (roll, yaw, pitch) deg and apex shift (x, y) mm of the rig finger's poses.
POSES = (((0.0, 0.0, 0.0), (0.0, 0.0)), ((3.0, -8.0, 4.0), (0.6, -0.5)),
         ((-4.0, 9.0, -3.0), (-0.8, 0.7)), ((2.0, 5.0, -6.0), (0.3, 0.4)),
         ((0.0, -4.0, 7.0), (0.0, 0.0)))
#: Largest median and 95th-percentile node residual (mm) against the skin coordinates
#: (without the pitch's estimate the pitched poses reach 0.07-0.11 and 0.18-0.32 mm).
MEDIAN_MM, P95_MM = 0.05, 0.13
#: Largest error of a cylinder node's x against its arc length (mm) beyond a pixel.
CYLINDER_MM = 0.05
#: Largest |scale - 1| of the similarity fit.
SCALE_TOLERANCE = 0.006


def _against_skin(unrolling: SurfaceUnrolling, rolled_mm: np.ndarray) -> tuple[float,
                                                                                np.ndarray]:
    """Scale and residuals of the nodes' layout (mirrored as a print is) against the skin
    coordinates at the nodes' pixels."""
    px = unrolling.node_pixel.astype(np.float32)
    skin = np.stack([cv2.remap(np.ascontiguousarray(rolled_mm[..., c], dtype=np.float32),
                               px[:, None, 0].copy(), px[:, None, 1].copy(),
                               cv2.INTER_LINEAR, borderValue=np.nan)[:, 0]
                     for c in range(2)], axis=1).astype(np.float64)
    known = np.isfinite(skin).all(axis=1)
    layout = unrolling.node_xy_mm * np.array([-1.0, 1.0])
    scale, rot, shift = similarity(layout[known], skin[known])
    return scale, np.linalg.norm(layout[known] @ (scale * rot).T + shift - skin[known], axis=1)


@pytest.fixture(scope="module", params=range(len(POSES)),
                ids=["front", "pose1", "pose2", "pitched_back", "pitched_forward"])
def rig_truth(request: pytest.FixtureRequest):
    (roll, yaw, pitch), (dx, dy) = POSES[request.param]
    x, y, z = FingertipShape().apex_optical_m
    rig = SimulatedRig(RigConfig(finger=FingertipShape(
        identity=3, roll_deg=roll, yaw_deg=yaw, pitch_deg=pitch,
        apex_optical_m=(x + dx * 1e-3, y + dy * 1e-3, z))))
    return rig, rig.finger_truth()


def test_the_rig_fingers_skin_coordinates(rig_truth) -> None:
    rig, truth = rig_truth
    results = {}
    for layout in Layout:
        unrolling = unroll_surface(truth.depth_m, mask=truth.mask,
                                   camera_matrix=rig.camera_matrix, layout=layout)
        results[layout] = _against_skin(unrolling, truth.rolled_mm)
    for layout, (scale, residual) in results.items():
        print(f"\n{layout.value}: scale {scale:.4f}, residual median "
              f"{np.median(residual):.3f} p95 {np.percentile(residual, 95):.3f} mm")
    scale, residual = results[Layout.ROLLED]
    assert abs(scale - 1.0) < SCALE_TOLERANCE
    assert np.median(residual) < MEDIAN_MM and np.percentile(residual, 95) < P95_MM
    # the springs' map is the other one: the rolled layout is the closer to the skin's
    assert np.percentile(residual, 95) < 0.5 * np.percentile(results[Layout.SPRINGS][1], 95)


def test_the_strain_figures_are_the_springs_whichever_layout(rig_truth) -> None:
    rig, truth = rig_truth
    springs, rolled = (unroll_surface(truth.depth_m, mask=truth.mask,
                                      camera_matrix=rig.camera_matrix, layout=layout)
                       for layout in (Layout.SPRINGS, Layout.ROLLED))
    assert rolled.strain_rms == springs.strain_rms and rolled.strain_max == springs.strain_max
    assert not np.allclose(rolled.node_xy_mm, springs.node_xy_mm, atol=0.05)


def test_a_cylinder_unrolls_to_its_arc_lengths() -> None:
    depth, mask, arc = cylinder()
    unrolling = unroll_surface(depth, mask=mask, camera_matrix=K, layout=Layout.ROLLED)
    px = np.rint(unrolling.node_pixel).astype(int)
    apex = int(np.argmin(unrolling.node_point_mm[:, 2]))  # the layout's origin
    true_s = arc[px[:, 1], px[:, 0], 0] - arc[px[apex, 1], px[apex, 0], 0]
    # the node pixels are block centres: the arc at the rounded pixel is within half a pixel
    pixel_mm = np.abs(np.gradient(arc[..., 0], axis=1))[px[:, 1], px[:, 0]]
    error = np.abs(unrolling.node_xy_mm[:, 0] - true_s) - pixel_mm
    print(f"\ncylinder: largest |x - arc| less a pixel {error.max():.4f} mm, median "
          f"{np.median(np.abs(unrolling.node_xy_mm[:, 0] - true_s)):.4f} mm")
    assert error.max() < CYLINDER_MM


@pytest.mark.parametrize("pitch_deg", [-8.0, -4.0, 0.0, 3.0, 8.0])
def test_the_pitch_is_the_crests_slope_where_the_cap_meets_the_pad(pitch_deg: float) -> None:
    # The rig finger's crest in its own frame: the cap's parabola (curvature 1 / (e^2 R))
    # towards the tip (t < 0), the pad's (1 / L) behind it; seen pitched, then sampled as
    # the layout samples it (0.25 mm), the apex off the knot.
    u = np.linspace(-9.0, 7.0, 400)
    w = np.where(u < 0, u * u / (2 * 1.15**2 * 8.0), u * u / (2 * 25.0))
    p = np.radians(pitch_deg)
    t_seen, z_seen = np.cos(p) * u - np.sin(p) * w, np.sin(p) * u + np.cos(p) * w
    t = np.arange(-8.0, 6.0, 0.25)
    depth = np.interp(t, t_seen, z_seen)
    depth[:3] = np.nan  # sections without a crest of their own
    estimate = np.degrees(crest_pitch(t, depth))
    print(f"\npitch {pitch_deg:+.1f} deg: estimated {estimate:+.2f}")
    assert abs(estimate - pitch_deg) < 0.3


def test_no_pitch_without_a_knot() -> None:
    t = np.arange(-8.0, 6.0, 0.25)
    # one curvature along the whole crest (a cylinder's bend, tilted): nothing to tell the
    # tip from the pad, so no pitch, whatever the slope
    assert crest_pitch(t, 0.1 * t + t * t / 50.0) == 0.0
    assert crest_pitch(t[:5], t[:5] ** 2) == 0.0  # too short a crest


def test_bad_input() -> None:
    triangles = cell_triangles(np.arange(81).reshape(9, 9))
    with pytest.raises(UnrollingError, match="at least 6"):
        rolled_layout(np.zeros((4, 3)), triangles[:1], 0, 0.5)
    s, t = np.meshgrid(np.linspace(-3, 3, 9), np.linspace(-3, 3, 9))
    trough = np.stack([s.ravel(), t.ravel(), 90.0 - 0.05 * s.ravel() ** 2], axis=1)
    with pytest.raises(UnrollingError, match="not convex across the finger"):
        rolled_layout(trough, triangles, 40, 0.75)
