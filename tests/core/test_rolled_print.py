"""Tests of surface.rolled_print: scale, polarity, format, bad input, the rig's finger.

Analytic case: the 8 mm cylinder of test_surface_unrolling carrying 50 um ridges along its
axis, crests every 0.5 mm of arc length. Simulated case: the rig's finger (true depth),
and a reconstruction of a simulated burst (as tests/core/test_pipeline.py runs it).

Measured (this machine): crest spacing on the cylinder 196.97 px per 10 mm (exact: 196.85);
the rig finger's print period 0.4962 mm (skin 0.5 mm; the estimator reads 0.4975 on the
generator's own pattern; 0.4855 with the springs layout, whose radial compression of the
doubly curved cap costs ~2.6 %, see test_surface_unrolling's sphere cap); agreement of a
reconstruction's print with the true ridges (correlation at the source pixels): Laplacian
0.965, relief 0.783 (0.98 both beyond 1 mm from the outline: the relief's band pass fails near it);
ridge-orientation coherence 0.97 on ridges, 0.29 on band-limited noise (limit 0.45);
egg-crate bumps (1 mm over 3 mm) unroll with 13 % rms strain (limit 5 %); with noise of
0.3 per component added to the normals, Gabor filtering raises the agreement 0.906 -> 0.937
(0.869 -> 0.955 with the band pass's former fine sigma of 0.06 mm and the springs layout).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
from test_surface_unrolling import APEX_MM, K, cylinder

from fingerps_driver.simulation import FingertipShape, RigConfig, Scene, SimulatedRig
from fingerps_recon.errors import FingerpsReconError, RolledPrintError
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.pipeline import Reconstruction, reconstruct
from fingerps_recon.photometric.pixel_rays import pixel_rays_optical
from fingerps_recon.surface.rolled_print import (
    PrintRejection,
    RidgeSignal,
    RolledPrint,
    RolledPrintOptions,
    rolled_print,
)

PERIOD_MM = 0.5
RIDGE_M = 50e-6
PX_PER_10_MM = 196.85
#: Tolerance of the 10 mm spacing, print pixels (1 %).
SCALE_TOLERANCE_PX = 2.0
#: The rig finger's print period may differ from the skin's by this fraction.
PERIOD_TOLERANCE = 0.05
#: Least correlation of a reconstruction's print with the true ridges (measured 0.965; the
#: relief's print 0.783).
AGREEMENT = 0.95
#: Noise added to each component of the reconstructed normals for the Gabor test.
NORMAL_NOISE = 0.3


def ridged_cylinder(*, noise: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth (m), mask and arc-length coordinates (mm) of the cylinder with raised ridges
    along its axis (crests at s = k * 0.5 mm), or with as much band-limited random relief."""
    depth, mask, arc = cylinder()
    if noise:
        rng = np.random.default_rng(3)
        field = scipy.ndimage.gaussian_filter(rng.standard_normal(depth.shape), 4.0)
        relief = 0.5 * RIDGE_M * field / field.std()
    else:
        relief = 0.5 * RIDGE_M * np.cos(2 * np.pi * arc[..., 0] / PERIOD_MM)
    return np.where(mask, depth - relief, np.nan), mask, arc


def normals_from_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals, PS frame, of the surface depth * ray (central differences)."""
    points = depth[..., None] * pixel_rays_optical(K, depth.shape)
    du = np.gradient(points, axis=1)
    dv = np.gradient(points, axis=0)
    n = np.cross(dv, du)  # towards the camera (optical -z) for a surface facing it
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.nan_to_num(optical_to_ps(n)).astype(np.float32)


def _print(depth: np.ndarray, mask: np.ndarray, **kwargs) -> RolledPrint:
    return rolled_print(depth, mask=mask, camera_matrix=K,
                        height_m=np.float32(APEX_MM / 1e3) - depth,
                        normals_ps=normals_from_depth(depth), **kwargs)


def _at_source(image: np.ndarray, result: RolledPrint) -> np.ndarray:
    """``image`` (source image plane) sampled at each print pixel of the mask."""
    coords = [result.source_y[result.mask], result.source_x[result.mask]]
    return scipy.ndimage.map_coordinates(image, coords, order=1, mode="nearest")


def dominant_period_mm(result: RolledPrint) -> float:
    """Peak of the radially averaged power spectrum of the print (zero-padded to 1024)."""
    x = np.where(result.mask, 255.0 - result.image, 0.0)
    x = np.where(result.mask, x - x[result.mask].mean(), 0.0)
    n = 1024
    power = np.abs(np.fft.fft2(x, (n, n))) ** 2
    radius = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]) * n
    ring = np.rint(radius).astype(int).ravel()
    profile = np.bincount(ring, power.ravel()) / np.maximum(np.bincount(ring), 1)
    lo, hi = int(0.05 * n), int(0.3 * n)
    k = lo + int(np.argmax(profile[lo:hi]))
    a, b, c = profile[k - 1:k + 2]
    peak = k + 0.5 * (a - c) / (a - 2 * b + c)
    return n / peak / result.px_per_mm


@pytest.fixture(scope="module")
def ridged() -> tuple[np.ndarray, np.ndarray, np.ndarray, RolledPrint]:
    depth, mask, arc = ridged_cylinder()
    return depth, mask, arc, _print(depth, mask)


def test_scale_is_500_ppi(ridged) -> None:
    _, _, _, result = ridged
    assert result.ppi == 500.0
    assert result.px_per_mm == pytest.approx(19.685, abs=1e-3)
    # Ridge crests (dark minima) along the print's middle row.
    rows = np.flatnonzero(result.mask.any(axis=1))
    row = (rows[0] + rows[-1]) // 2
    profile = result.image[row - 2:row + 3].astype(np.float64).mean(axis=0)
    inside = result.mask[row]
    x_mm = result.origin_mm[0] + np.arange(profile.size) / result.px_per_mm
    minima = np.flatnonzero((profile[1:-1] < profile[:-2]) & (profile[1:-1] <= profile[2:])
                            & (profile[1:-1] < 80) & inside[1:-1]) + 1
    minima = minima[np.abs(x_mm[minima]) <= 6.0]  # within 43 deg of the cylinder's apex
    a, b, c = profile[minima - 1], profile[minima], profile[minima + 1]
    crest = minima + 0.5 * (a - c) / (a - 2 * b + c)
    index = np.rint((crest - crest[0]) / (PERIOD_MM * result.px_per_mm))
    assert np.array_equal(index, np.arange(index.size)), "a crest is missing or extra"
    pitch = np.polyfit(index, crest, 1)[0]
    print(f"\ncylinder: {index.size} crests, {20 * pitch:.2f} px per 10 mm "
          f"(500 ppi: {PX_PER_10_MM})")
    assert abs(20 * pitch - PX_PER_10_MM) <= SCALE_TOLERANCE_PX


@pytest.mark.parametrize("signal", list(RidgeSignal))
def test_raised_ridges_come_out_dark(ridged, signal: RidgeSignal) -> None:
    depth, mask, arc, result = ridged
    if signal is not RolledPrintOptions().signal:
        result = _print(depth, mask, options=RolledPrintOptions(signal=signal))
    crest = np.cos(2 * np.pi * arc[..., 0] / PERIOD_MM)  # +1 on a ridge's crest
    phase = _at_source(crest, result)
    grey = result.image[result.mask]
    dark, light = phase[grey < 64], phase[grey > 192]
    print(f"\n{signal.value}: crest phase of dark pixels {dark.mean():+.2f}, light "
          f"{light.mean():+.2f}")
    assert dark.size > 1000 and light.size > 1000
    assert dark.mean() > 0.7 and light.mean() < -0.7


def test_print_format(ridged) -> None:
    _, _, _, result = ridged
    assert result.image.dtype == np.uint8 and result.mask.dtype == bool
    assert result.image.shape == result.mask.shape == result.source_x.shape
    assert np.all(result.image[~result.mask] == 255)
    assert 100 < result.image[result.mask].mean() < 160
    assert np.isfinite(result.source_x[result.mask]).all()
    # The cylinder shows 2 * 8 mm * 65 deg = 18.2 mm around by ~14.8 mm along.
    print(f"\ncylinder print: {result.image.shape}, {result.area_mm2:.0f} mm^2, coherence "
          f"{result.coherence:.2f}, {result.timings_ms}")
    assert 215 < result.area_mm2 < 270  # less a 0.2 mm trim along the outline
    assert result.coherence > 0.9
    assert result.strain_rms < 1e-3


def test_the_border_is_white_margin_around_the_same_print(ridged) -> None:
    depth, mask, _, result = ridged
    narrow = _print(depth, mask, options=RolledPrintOptions(border_px=8))
    extra = RolledPrintOptions().border_px - 8
    assert extra > 0
    inner = (slice(extra, -extra), slice(extra, -extra))
    np.testing.assert_array_equal(result.image[inner], narrow.image)
    np.testing.assert_array_equal(result.mask[inner], narrow.mask)
    np.testing.assert_array_equal(result.source_x[inner], narrow.source_x)
    assert np.all(result.image[:extra] == 255) and not result.mask[:, :extra].any()
    assert np.isnan(result.source_y[-extra:]).all()
    np.testing.assert_allclose(result.origin_mm, np.subtract(narrow.origin_mm,
                                                             extra / result.px_per_mm))


def test_the_grey_gain_scales_the_ridges_contrast(ridged) -> None:
    depth, mask, _, result = ridged
    soft = _print(depth, mask, options=RolledPrintOptions(grey_gain=0.5 * RolledPrintOptions()
                                                          .grey_gain))
    assert np.array_equal(soft.mask, result.mask)
    spread = [np.subtract(*np.percentile(p.image[p.mask].astype(float), [95, 5]))
              for p in (result, soft)]
    print(f"\ngrey p5-p95 spread {spread[0]:.0f} (gain {RolledPrintOptions().grey_gain}), "
          f"{spread[1]:.0f} (half)")
    assert spread[1] == pytest.approx(0.5 * spread[0], rel=0.05)
    assert abs(np.mean(soft.image[soft.mask]) - 127.5) < 10


def test_print_is_the_mirror_of_the_camera_view(ridged) -> None:
    """Legacy orientation (a contact print is the skin's mirror image): along a print row
    the source column falls, down a print column the source row rises; ``origin_mm`` is in
    print x = minus the unrolled x."""
    _, _, _, result = ridged
    row = int(np.flatnonzero(result.mask.any(axis=1)).mean())
    col = int(np.flatnonzero(result.mask.any(axis=0)).mean())
    along = result.source_x[row, result.mask[row]]
    down = result.source_y[result.mask[:, col], col]
    assert np.all(np.diff(along) < 0.0) and np.all(np.diff(down) > 0.0)
    unrolled = result.unrolling.pixel_xy_mm
    i, j = row, np.flatnonzero(result.mask[row])[len(along) // 3]
    u, v = round(float(result.source_x[i, j])), round(float(result.source_y[i, j]))
    print_x = result.origin_mm[0] + j / result.px_per_mm
    assert print_x == pytest.approx(-unrolled[v, u, 0], abs=0.05)


def test_too_little_finger() -> None:
    depth, mask, arc = ridged_cylinder()
    small = mask & (np.hypot(arc[..., 0], arc[..., 1]) < 3.0)  # ~28 mm^2
    with pytest.raises(RolledPrintError, match="mm\\^2") as info:
        _print(depth, small)
    assert info.value.reason is PrintRejection.TOO_SMALL
    with pytest.raises(RolledPrintError) as info:
        _print(depth, np.zeros_like(mask))
    assert info.value.reason is PrintRejection.TOO_SMALL


def test_inputs_that_do_not_fit() -> None:
    depth, mask, _ = ridged_cylinder()
    with pytest.raises(FingerpsReconError, match="same"):
        _print(depth, mask[:-1])
    with pytest.raises(FingerpsReconError, match="normals_ps"):
        rolled_print(depth, mask=mask, camera_matrix=K)  # the Laplacian needs the normals


def test_noise_is_not_a_print() -> None:
    depth, mask, _ = ridged_cylinder(noise=True)
    with pytest.raises(RolledPrintError, match="coherence") as info:
        _print(depth, mask)
    assert info.value.reason is PrintRejection.TOO_NOISY


def test_a_distorted_shape_is_not_unrolled() -> None:
    depth, mask, arc = cylinder()
    # Egg-crate bumps of 1 mm over 3 mm: far from developable.
    bumps = 1e-3 * np.sin(2 * np.pi * arc[..., 0] / 3.0) * np.sin(2 * np.pi * arc[..., 1] / 3.0)
    with pytest.raises(RolledPrintError, match="strain") as info:
        _print(depth + bumps, mask)
    assert info.value.reason is PrintRejection.TOO_STRAINED


def test_rig_finger_period() -> None:
    rig = SimulatedRig(RigConfig(finger=FingertipShape(ridge_ellipticity=1.0)))
    truth = rig.finger_truth()
    result = rolled_print(truth.depth_m, mask=truth.mask, camera_matrix=rig.camera_matrix,
                          normals_ps=truth.normals_ps)
    period = dominant_period_mm(result)
    print(f"\nrig finger: period {period:.4f} mm (skin {1e3 * rig.fingertip.ridge_period_m} mm), "
          f"area {result.area_mm2:.0f} mm^2, strain rms {100 * result.strain_rms:.2f} % max "
          f"{100 * result.strain_max:.1f} %, coherence {result.coherence:.3f}")
    assert abs(period / (1e3 * rig.config.finger.ridge_period_m) - 1) <= PERIOD_TOLERANCE
    assert result.coherence > 0.9


@pytest.fixture(scope="module")
def rig_case() -> tuple[SimulatedRig, Reconstruction, np.ndarray]:
    """The rig, a reconstruction of its burst (as tests/core/test_pipeline.py makes it) and
    the true ridges on the image: how far each pixel's surface point is raised above the
    same finger without ridges (positive on the crests)."""
    rig = SimulatedRig()
    truth = rig.finger_truth()
    images = rig.render_burst(Scene.FINGER, seed=10)
    recon = reconstruct(images, lights_ps=rig.light_directions_ps(),
                        camera_matrix=rig.camera_matrix, full_scale=255.0,
                        intensities=rig.light_intensities())
    plain = SimulatedRig(RigConfig(finger=FingertipShape(ridge_height_m=0.0))).finger_truth()
    ridges = np.where(truth.mask & plain.mask, plain.depth_m - truth.depth_m, 0.0)
    return rig, recon, ridges


def _agreement(result: RolledPrint, ridges: np.ndarray) -> float:
    """Correlation of the print's darkness with the true ridges at its source pixels."""
    darkness = 255.0 - result.image[result.mask]
    return float(np.corrcoef(darkness, _at_source(ridges, result))[0, 1])


def test_reconstruction_print_follows_the_true_ridges(rig_case) -> None:
    """The print of a reconstructed burst agrees with the true ridges, and the default
    ridge signal (the normals' Laplacian) agrees better than the relief."""
    rig, recon, ridges = rig_case
    agreement = {}
    for signal in RidgeSignal:
        result = rolled_print(recon.depth_m, mask=recon.mask, camera_matrix=rig.camera_matrix,
                              height_m=recon.height_m, normals_ps=recon.normals_ps,
                              options=RolledPrintOptions(signal=signal))
        agreement[signal] = _agreement(result, ridges)
        print(f"\n{signal.value}: agreement {agreement[signal]:.3f}, coherence "
              f"{result.coherence:.3f}, area {result.area_mm2:.0f} mm^2, strain rms "
              f"{100 * result.strain_rms:.2f} %, {result.timings_ms['total']:.0f} ms")
    assert agreement[RidgeSignal.LAPLACIAN] > AGREEMENT
    assert agreement[RidgeSignal.LAPLACIAN] > agreement[RidgeSignal.HEIGHT] + 0.05


def test_gabor_filtering_helps_noisy_normals(rig_case) -> None:
    rig, recon, ridges = rig_case
    noisy = recon.normals_ps + NORMAL_NOISE * np.random.default_rng(5).standard_normal(
        recon.normals_ps.shape).astype(np.float32)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    noisy[~recon.mask] = 0.0
    agreement = {}
    for gabor in (False, True):
        result = rolled_print(recon.depth_m, mask=recon.mask, camera_matrix=rig.camera_matrix,
                              normals_ps=noisy, options=RolledPrintOptions(gabor=gabor))
        agreement[gabor] = _agreement(result, ridges)
        print(f"\ngabor {gabor}: agreement {agreement[gabor]:.3f}, coherence "
              f"{result.coherence:.3f}, enhance {result.timings_ms['enhance']:.0f} ms")
    assert agreement[True] > agreement[False] + 0.02
