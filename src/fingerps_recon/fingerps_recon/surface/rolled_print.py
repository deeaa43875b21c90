"""The rolled-equivalent 500 ppi fingerprint of a reconstruction.

Matchers (AFIS, NIST NBIS, commercial SDKs) take a 500 ppi grey-scale print with dark
ridges, as an ink roll or a contact sensor gives it. Following Chen, Parziale,
Diaz-Santana & Jain, "3D touchless fingerprints: compatibility with legacy rolled images"
(Biometric Consortium Conference, 2006), the 3D surface is unrolled onto a plane that keeps
distances along the skin (:mod:`fingerps_recon.surface.surface_unrolling`) and the ridge relief is
resampled onto that plane. Steps of :func:`rolled_print`:

1. Ridge signal on the image (:class:`RidgeSignal`): the Laplacian of the relief from the
   normals (the divergence of the slope field p = -nx/nz, q = -ny/nz in metric units,
   negated so that ridges, raised towards the camera, are positive), or the relief
   ``height_m`` itself. Measured on a reconstruction of the simulated rig's burst, the
   Laplacian's print agrees better with the true ridges (correlation 0.97 against 0.78;
   ``tests/core/test_rolled_print.py``; also with noise added to the normals): the relief
   carries the finger's whole shape, whose curvature the band pass cannot remove where its
   window is cut by the outline, and leaves a smeared band along it (both give 0.98 beyond
   1 mm from the outline). The Laplacian is the default.
2. Unrolling and resampling at exactly ``ppi`` (19.685 px/mm at 500 ppi) with
   ``cv2.remap`` through the inverse map of the unrolling, mirrored left-right (below). The
   plane is by default the rolled finger's (``Layout.ROLLED``,
   :mod:`fingerps_recon.surface.rolled_layout`: arc lengths around the finger along its
   sections and along it, as rolling it on a card lays the skin out), the plane rolled and
   contact prints are in; the springs model (``Layout.SPRINGS``), which keeps every
   neighbour distance as well as it can, spreads the cap's strain differently, by up to
   ~6 % at the print's edge. On the fingerprint benchmark's HK captures the rolled plane
   (with the finger's pitch) put every 4 mm region of the print within 0.92 % of the scale
   of the finger's true rolled plane (springs: 6.7 %) and the median distance left after a
   similarity fit at 0.020 mm (0.19 mm); recall / precision 0.987 / 0.976, NFIQ 2 median
   55, bozorth3 against contact impressions 0.88 of contact-vs-contact (issue 23).
3. Band pass on the print plane, where the ridge period is the skin's: a difference of
   Gaussians (sigma 0.1 and 0.3 mm: half its peak gain at periods of 0.43 and 1.9 mm, 6 % at
   0.25 mm), as normalized convolutions within the print's mask, so the outside does not
   enter; the windows of 0.3 mm and more are computed at half resolution (250 ppi), where
   they are well sampled. The fine sigma removes the ridges' harmonics (half the ridge
   period: the Laplacian of a ridge is sharper than a sine) and the normals' noise, which
   mindtct took for ridge breaks. On the fingerprint benchmark's 60 HK captures, mindtct's
   recall / precision of the true minutiae went from 0.925 / 0.911 with 0.06 mm to 0.991 /
   0.976 with 0.1 mm; the print of the TRUE surface did no better than the reconstruction's
   with 0.06 mm (0.883 / 0.872 on 12 captures; 0.987 / 0.974 with 0.1 mm): the print's
   rendering, not the normals, had set the limit (issue 23).
4. Local contrast normalisation: zero mean and unit standard deviation in ~1 mm windows
   (Gaussian sigma 0.4 mm), then ridges dark on white: grey = 127.5 (1 - g n) clipped to
   0..255, g = ``RolledPrintOptions.grey_gain`` = 0.375 (a sinusoidal ridge spans
   ~60..195), 255 outside the finger. Optionally
   contextual Gabor filtering before the grey levels (``RolledPrintOptions.gabor``).

Orientation: the legacy one of rolled and contact prints, which matchers' galleries hold.
A print is the mirror image of the skin seen from outside (the skin touches the card or
the platen, as a stamp does), while the camera sees the skin from outside, so the print is
the camera's view mirrored left-right: with the finger pointing up the image, print x
(right) is minus the unrolled x of :mod:`fingerps_recon.surface.surface_unrolling` (which keeps the
camera's view), print y (down) is the unrolled y. The simulated rig follows the same
convention (``fingerps_driver.simulation.fingertip``: the skin carries its ground-truth
rolled print mirrored), so a print of the rig's finger matches ``rig.rolled_print()`` up to
a small similarity transform, without a flip (``bench/bench_fingerprint.py``: bozorth3).

Quality facts: the print's area (mm^2), the unrolling's strain (rms and max relative
difference of 2D and 3D spring lengths) and the mean ridge-orientation coherence of the
print (Bazen & Gerez, "Systematic methods for the computation of the directional fields
and singular points of fingerprints", IEEE TPAMI 24(7), 2002: |l1 - l2| / (l1 + l2) of
the gradient structure tensor in ~1 mm windows; ~0.9 for clean ridges, ~0.2 for noise).
A reconstruction too small, too strained or too noisy to give a print raises
:class:`RolledPrintError` with its :class:`PrintRejection` reason, never a garbage print.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from enum import Enum

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError, RolledPrintError, UnrollingError
from fingerps_recon.photometric.pixel_rays import checked_camera_matrix
from fingerps_recon.surface import print_kernel
from fingerps_recon.surface.surface_unrolling import Layout, SurfaceUnrolling, unroll_surface

MM_PER_INCH = 25.4
# Print pixels whose source neighbourhood is at least this fraction inside the mask.
_MIN_WEIGHT = 0.999
# Margin the print is computed with (the rest of ``border_px`` is padding: white, off).
_WORK_BORDER_PX = 8
# Steepest normal used for the slopes p, q (nz below it is clamped).
_MIN_NZ = 0.1


class RidgeSignal(Enum):
    """What the print's grey values are made from."""

    HEIGHT = "height"        # the relief height_m, band-passed on the print plane
    LAPLACIAN = "laplacian"  # -div(p, q) of the normals' slopes: minus the relief's Laplacian


class PrintRejection(Enum):
    """Why a reconstruction gives no print."""

    TOO_SMALL = "too_small"        # too little finger area
    TOO_STRAINED = "too_strained"  # the surface does not unroll without stretching the skin
    TOO_NOISY = "too_noisy"        # no coherent ridges


@dataclass(frozen=True)
class RolledPrintOptions:
    """Options of :func:`rolled_print`; the limits suit the simulated rig."""

    ppi: float = 500.0
    signal: RidgeSignal = RidgeSignal.LAPLACIAN
    band_sigmas_mm: tuple[float, float] = (0.1, 0.3)
    """Difference of Gaussians on the print plane (fine, coarse), millimetres."""
    normalisation_sigma_mm: float = 0.4
    """Gaussian window of the local mean and standard deviation (~1 mm across)."""
    grey_gain: float = 0.375
    """Grey levels per unit of the normalised signal, over 127.5 (step 4). On the prints of
    the fingerprint benchmark's 60 TRUE surfaces, bozorth3 against contact impressions went
    from 0.85 of contact-vs-contact with 0.5 to 0.92 with 0.375 (0.91 with 0.25 and 0.325,
    0.89 with 0.425; NFIQ 2 median 54-56 throughout): mindtct finds fewer minutiae along the
    print's outline in the softer print (issue 23)."""
    mesh_spacing_mm: float = 0.5
    layout: Layout = Layout.ROLLED
    """The unrolled plane: the rolled finger's (arc lengths around and along it, as rolling
    it on a card lays it out) or the springs' (``surface_unrolling``)."""
    border_px: int = 24
    """White margin around the finger, print pixels. mindtct finds fewer minutiae near the
    image's edge (its maps are of 8 px blocks in 24 px windows): on the fingerprint
    benchmark's prints of the rig's TRUE surfaces (20 fingers x 3), bozorth3 against contact
    impressions went from 0.78 of contact-vs-contact with 8 px to 0.83 with 24 px and more
    (issue 23). The print is computed with at most ``_WORK_BORDER_PX`` and padded."""
    trim_mm: float = 0.2
    """Band along the outline left out of the print (the signal's derivatives and the band
    pass are unreliable within ~0.25 mm of the outline)."""
    min_area_mm2: float = 40.0
    max_strain_rms: float = 0.05
    """A finger's cap unrolls with ~1-3 % rms strain; a 65 deg sphere cap 3.6 %."""
    max_strain: float = 0.5
    min_coherence: float = 0.45
    max_size_mm: float = 60.0
    gabor: bool = False
    """Contextual (Gabor) filtering after the normalisation. On the simulated rig it helps
    only noisy normals (agreement with the true ridges 0.91 -> 0.94 with normals noise of
    0.3 per component) and costs a filter bank per print; on clean ones it did not help
    mindtct (12 benchmark captures, with the former fine sigma of 0.06 mm: recall /
    precision 0.885 / 0.867 with it, 0.882 / 0.875 without), so it is off by default."""
    gabor_period_mm: float = 0.5
    """Ridge period the Gabor filters are tuned to (their band is ~+-30 %)."""


@dataclass(frozen=True)
class RolledPrint:
    """A rolled-equivalent print (see the module docstring).

    Attributes
    ----------
    image : (Ho, Wo) uint8
        Ridges dark on white, 255 outside the finger; the legacy orientation, the mirror
        image of the camera's view (module docstring).
    mask : (Ho, Wo) bool
        Print pixels on the finger.
    ppi : float
        Resolution, pixels per inch (the pixel pitch is 25.4 / ppi mm).
    origin_mm : (2,) float
        Print-plane (x, y) of the centre of print pixel (0, 0), millimetres; x right, y
        down, the apex (the point nearest the camera) at (0, 0). Print x is minus the
        unrolled x (``unrolling``'s, the camera's view): the print is its mirror image.
    source_x, source_y : (Ho, Wo) float32
        Source image column and row of each print pixel; NaN off the unrolled surface.
    area_mm2 : float
        Area of ``mask`` on the skin.
    strain_rms, strain_max : float
        Spring strain of the unrolling (relative 2D vs 3D length difference).
    coherence : float
        Mean ridge-orientation coherence over the print, 0..1.
    unrolling : SurfaceUnrolling
    timings_ms : dict
    """

    image: np.ndarray
    mask: np.ndarray
    ppi: float
    origin_mm: tuple[float, float]
    source_x: np.ndarray
    source_y: np.ndarray
    area_mm2: float
    strain_rms: float
    strain_max: float
    coherence: float
    unrolling: SurfaceUnrolling
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def px_per_mm(self) -> float:
        return self.ppi / MM_PER_INCH


def rolled_print(
    depth_m: np.ndarray,
    *,
    mask: np.ndarray,
    camera_matrix: np.ndarray,
    height_m: np.ndarray | None = None,
    normals_ps: np.ndarray | None = None,
    options: RolledPrintOptions = RolledPrintOptions(),
) -> RolledPrint:
    """Rolled-equivalent print of a reconstruction (see the module docstring).

    Parameters
    ----------
    depth_m : (H, W) float
        Optical z, metres; NaN outside the finger (``Reconstruction.depth_m``).
    mask : (H, W) bool
        Finger pixels.
    camera_matrix : (3, 3) float
        Pinhole intrinsics K.
    height_m : (H, W) float, optional
        Relief towards the camera (``Reconstruction.height_m``), for ``RidgeSignal.HEIGHT``
        (default: minus the depth).
    normals_ps : (H, W, 3) float, optional
        Unit normals, PS frame (``Reconstruction.normals_ps``); needed for
        ``RidgeSignal.LAPLACIAN`` (the default).
    options : RolledPrintOptions

    Returns
    -------
    RolledPrint

    Raises
    ------
    RolledPrintError
        Too little finger, too much strain, no coherent ridges (``reason``).
    """
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    k = checked_camera_matrix(camera_matrix)
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2 or np.shape(mask) != depth.shape:
        raise FingerpsReconError(f"depth_m {depth.shape} and mask {np.shape(mask)} must be "
                                 "the same (H, W) shape")
    valid = np.asarray(mask, dtype=bool) & np.isfinite(depth)
    signal, (row0, col0) = _ridge_signal(depth, valid, k, height_m, normals_ps, options.signal)
    timings["signal"] = (time.perf_counter() - t0) * 1e3

    t1 = time.perf_counter()
    try:
        unrolling = unroll_surface(depth, mask=valid, camera_matrix=k,
                                   spacing_mm=options.mesh_spacing_mm, layout=options.layout)
    except UnrollingError as error:
        raise RolledPrintError(
            PrintRejection.TOO_SMALL,
            f"the reconstruction cannot be unrolled ({error}); place more of the finger "
            "in view") from error
    timings["unroll"] = (time.perf_counter() - t1) * 1e3
    if (unrolling.strain_rms > options.max_strain_rms
            or unrolling.strain_max > options.max_strain):
        raise RolledPrintError(
            PrintRejection.TOO_STRAINED,
            f"the surface unrolls with {100 * unrolling.strain_rms:.1f} % rms strain "
            f"(max {100 * unrolling.strain_max:.0f} %; limits "
            f"{100 * options.max_strain_rms:.0f} %, {100 * options.max_strain:.0f} %): the "
            "reconstructed shape is distorted or folded; hold the finger still and retake")

    t1 = time.perf_counter()
    ppmm = options.ppi / MM_PER_INCH
    x_min, x_max, y_min, y_max = unrolling.bounds_mm
    if max(x_max - x_min, y_max - y_min) > options.max_size_mm:
        raise RolledPrintError(
            PrintRejection.TOO_STRAINED,
            f"the unrolled surface spans {x_max - x_min:.0f} x {y_max - y_min:.0f} mm, more "
            f"than a finger ({options.max_size_mm:.0f} mm): the reconstruction is distorted")
    b = min(int(options.border_px), _WORK_BORDER_PX)
    c0 = math.floor(x_min * ppmm) - b
    r0 = math.floor(y_min * ppmm) - b
    cols = np.arange(c0, math.ceil(x_max * ppmm) + b + 1)
    rows = np.arange(r0, math.ceil(y_max * ppmm) + b + 1)
    src_x, src_y = unrolling.source_pixels(cols / ppmm, rows / ppmm)
    off = ~np.isfinite(src_x) | ~np.isfinite(src_y)
    # The legacy orientation (module docstring): print column j shows unrolled x = -x_j.
    src_x, src_y, off = (np.ascontiguousarray(a[:, ::-1]) for a in (src_x, src_y, off))
    src_x[off] = -1e4
    src_y[off] = -1e4
    # From the signal's box (one-channel remaps: OpenCV interpolates them in float; with
    # more channels in fixed point, 1/32 px).
    box = (slice(row0, row0 + signal.shape[0]), slice(col0, col0 + signal.shape[1]))
    box_x, box_y = src_x - np.float32(col0), src_y - np.float32(row0)
    weight, sig = (cv2.remap(image, box_x, box_y, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                   for image in (valid[box].astype(np.float32), signal))
    inside = weight >= _MIN_WEIGHT
    trim = round(options.trim_mm * ppmm)
    if trim > 0:
        inside = cv2.erode(inside.astype(np.uint8), cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * trim + 1, 2 * trim + 1))).astype(bool)
    src_x[off] = np.nan
    src_y[off] = np.nan
    timings["resample"] = (time.perf_counter() - t1) * 1e3

    area = float(inside.sum()) / ppmm**2
    if area < options.min_area_mm2:
        raise RolledPrintError(
            PrintRejection.TOO_SMALL,
            f"only {area:.0f} mm^2 of finger (at least {options.min_area_mm2:.0f} mm^2 "
            "needed for a print): place the fingertip's pad in view")

    t1 = time.perf_counter()
    image, coherence = _enhance(np.where(inside, sig / np.maximum(weight, 1e-6), 0.0),
                                inside, ppmm, options)
    timings["enhance"] = (time.perf_counter() - t1) * 1e3
    if coherence < options.min_coherence:
        raise RolledPrintError(
            PrintRejection.TOO_NOISY,
            f"the ridges are not coherent (mean orientation coherence {coherence:.2f}, at "
            f"least {options.min_coherence:.2f} needed): the reconstruction is too noisy or "
            "blurred; check focus, exposure and that the finger holds still")
    pad = max(int(options.border_px) - b, 0)
    if pad:
        image = np.pad(image, pad, constant_values=255)
        inside = np.pad(inside, pad, constant_values=False)
        src_x, src_y = (np.pad(a, pad, constant_values=np.nan) for a in (src_x, src_y))
    timings["total"] = (time.perf_counter() - t0) * 1e3
    return RolledPrint(
        image=image, mask=inside, ppi=float(options.ppi),
        origin_mm=(-float(cols[-1] + pad) / ppmm, (r0 - pad) / ppmm),
        source_x=src_x, source_y=src_y, area_mm2=area, strain_rms=unrolling.strain_rms,
        strain_max=unrolling.strain_max, coherence=coherence, unrolling=unrolling,
        timings_ms=timings)


def _ridge_signal(depth: np.ndarray, valid: np.ndarray, k: np.ndarray,
                  height_m: np.ndarray | None, normals_ps: np.ndarray | None,
                  kind: RidgeSignal) -> tuple[np.ndarray, tuple[int, int]]:
    """Ridge signal (positive on ridges, arbitrary units), float32, 0 off ``valid``, on the
    box of ``valid`` and one pixel around it; and the box's first (row, column). ``valid``
    is narrowed in place where the signal is undefined."""
    if kind is RidgeSignal.HEIGHT:
        if height_m is not None and np.shape(height_m) != depth.shape:
            raise FingerpsReconError(f"height_m {np.shape(height_m)} differs from depth_m "
                                     f"{depth.shape}")
    elif normals_ps is None or np.shape(normals_ps) != (*depth.shape, 3):
        raise FingerpsReconError(
            f"RidgeSignal.LAPLACIAN needs normals_ps of shape {(*depth.shape, 3)}, got "
            f"{None if normals_ps is None else np.shape(normals_ps)}")
    rows = np.flatnonzero(valid.any(axis=1))
    cols = np.flatnonzero(valid.any(axis=0))
    if rows.size == 0:
        return np.zeros(depth.shape, dtype=np.float32), (0, 0)
    box = (slice(max(rows[0] - 1, 0), rows[-1] + 2), slice(max(cols[0] - 1, 0), cols[-1] + 2))
    origin = (box[0].start, box[1].start)
    depth, valid = depth[box], valid[box]  # a view: narrowing it narrows the caller's
    if kind is RidgeSignal.HEIGHT:
        if height_m is None:
            relief = -1e3 * depth  # nearer = higher, millimetres
        else:
            relief = 1e3 * np.asarray(height_m, dtype=np.float32)[box]
        valid &= np.isfinite(relief)
        return np.where(valid, relief, 0.0).astype(np.float32), origin
    # Metric pixel size z / f: one depth for all pixels (the finger's depth varies by a few
    # per cent, and the local normalisation removes the overall scale); fx and fy may differ.
    z_mm = 1e3 * float(np.median(depth[valid][::7]))
    dx_mm, dy_mm = z_mm / k[0, 0], z_mm / k[1, 1]
    signal = np.empty(valid.shape, dtype=np.float32)
    keep = np.empty(valid.shape, dtype=bool)
    print_kernel.ridge_laplacian(np.asarray(normals_ps, dtype=np.float32)[box], valid,
                                 np.float32(_MIN_NZ), np.float32(0.5 / dx_mm),
                                 np.float32(0.5 / dy_mm), signal, keep)
    valid &= keep
    return signal, origin


def _enhance(signal: np.ndarray, inside: np.ndarray, ppmm: float,
             options: RolledPrintOptions) -> tuple[np.ndarray, float]:
    """Band pass, local normalisation and grey levels on the print plane; the mean
    orientation coherence.

    The smoothings of 0.3 mm and more (the band pass's coarse Gaussian, the normalisation's
    and the structure tensor's windows) run at half resolution (:class:`_HalfScale`); the
    fine Gaussian of the band pass at full resolution."""
    w = inside.astype(np.float32)
    s = signal.astype(np.float32)
    half = _HalfScale(w)
    fine_mm, coarse_mm = options.band_sigmas_mm
    sigma = fine_mm * ppmm
    fine = (cv2.GaussianBlur(s * w, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
            / np.maximum(cv2.GaussianBlur(w, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT),
                         1e-6))
    band = fine - half.smooth(s, coarse_mm * ppmm)
    sn = options.normalisation_sigma_mm * ppmm
    centred = band - half.smooth(band, sn)
    var = half.smooth(centred * centred, sn)
    floor = float(np.median(var[inside])) * 0.01 if inside.any() else 1.0
    norm = centred / np.sqrt(var + max(floor, 1e-30))

    # Gradient structure tensor (Bazen & Gerez 2002) over the same windows.
    gx = cv2.Sobel(norm, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(norm, cv2.CV_32F, 0, 1, ksize=3)
    core = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    gx *= core
    gy *= core
    # At half resolution: the mean coherence over the core needs no finer sampling.
    gxx, gyy, gxy = (half.smooth(g, sn, up=False) for g in (gx * gx, gy * gy, gx * gy))
    coherence = np.sqrt((gxx - gyy) ** 2 + 4 * gxy * gxy) / np.maximum(gxx + gyy, 1e-12)
    core_half = half.down(core.astype(np.float32)) > 0.999  # all four pixels in the core

    if options.gabor:
        # Across the ridges: the direction of the structure tensor's main eigenvector.
        gxx, gyy, gxy = (half.up(t) for t in (gxx, gyy, gxy))
        across = 0.5 * np.arctan2(2 * gxy, gxx - gyy)
        norm = _gabor(np.where(inside, norm, 0.0).astype(np.float32), inside, across,
                      options.gabor_period_mm * ppmm)
    grey = np.clip(127.5 * (1.0 - options.grey_gain * norm), 0.0, 255.0)
    image = np.where(inside, np.rint(grey), 255.0).astype(np.uint8)
    return image, float(coherence[core_half].mean()) if core_half.any() else 0.0


class _HalfScale:
    """Normalized Gaussian convolution within the weights ``w`` (Knutsson & Westin 1993:
    blur(x w) / blur(w)) computed at half resolution: 2x2 means down, the Gaussian, bilinear
    up. The means and the interpolation add 1/4 and 3/4 px^2 of variance, so the Gaussian's
    is sigma^2 - 1 (full-resolution pixels). Meant for sigma >= ~5 px (0.25 mm at 500 ppi):
    on prints of the simulated rig the grey levels then stay within 3 of those smoothed at
    full resolution."""

    def __init__(self, w: np.ndarray) -> None:
        self.shape = w.shape
        h, wd = w.shape
        self._pad = (h % 2, wd % 2)  # even sizes: half-resolution pixel i covers 2i, 2i+1
        self.w = w
        self.w_half = self.down(w)
        self._den: dict[float, np.ndarray] = {}

    def down(self, x: np.ndarray) -> np.ndarray:
        """2x2 means of ``x`` (zero-padded to even sizes)."""
        if any(self._pad):
            x = cv2.copyMakeBorder(x, 0, self._pad[0], 0, self._pad[1], cv2.BORDER_CONSTANT)
        return cv2.resize(x, (x.shape[1] // 2, x.shape[0] // 2), interpolation=cv2.INTER_AREA)

    def up(self, x: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of a half-resolution ``x`` at the full-resolution pixels."""
        h, wd = self.shape
        return cv2.resize(x, (x.shape[1] * 2, x.shape[0] * 2),
                          interpolation=cv2.INTER_LINEAR)[:h, :wd]

    def smooth(self, x: np.ndarray, sigma_px: float, *, up: bool = True) -> np.ndarray:
        """(H, W) float32 normalized blur of ``x`` (sigma in full-resolution px); at half
        resolution if not ``up``."""
        sigma = 0.5 * math.sqrt(max(sigma_px * sigma_px - 1.0, 0.25))
        if sigma not in self._den:
            self._den[sigma] = np.maximum(cv2.GaussianBlur(
                self.w_half, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT), 1e-6)
        ratio = cv2.GaussianBlur(self.down(x * self.w), (0, 0), sigma,
                                 borderType=cv2.BORDER_CONSTANT)
        ratio /= self._den[sigma]
        return self.up(ratio) if up else ratio


def _gabor(x: np.ndarray, inside: np.ndarray, across: np.ndarray, period_px: float,
           count: int = 8) -> np.ndarray:
    """Contextual filtering as in Hong, Wan & Jain, "Fingerprint image enhancement:
    algorithm and performance evaluation", IEEE TPAMI 20(8), 1998: each pixel takes the
    response of the even-symmetric Gabor filter across its local ridge direction
    (``across``, radians, image axes) at the ridge period, interpolated between the two
    nearest of ``count`` orientations; then unit rms over ``inside``."""
    sigma = 0.5 * period_px
    size = 2 * math.ceil(3 * sigma) + 1
    responses = np.empty((count, *x.shape), dtype=np.float32)
    for i in range(count):  # one filter per orientation, not per pixel
        kernel = cv2.getGaborKernel((size, size), sigma, np.pi * i / count, period_px, 1.0, 0.0,
                                    ktype=cv2.CV_32F)
        kernel -= kernel.mean()  # no response to a constant
        responses[i] = cv2.filter2D(x, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
    position = np.mod(across, np.pi) * (count / np.pi)
    lower = np.floor(position).astype(np.intp)
    frac = (position - lower).astype(np.float32)
    r0 = np.take_along_axis(responses, (lower % count)[None], 0)[0]
    r1 = np.take_along_axis(responses, ((lower + 1) % count)[None], 0)[0]
    out = (1.0 - frac) * r0 + frac * r1
    rms = float(np.sqrt(np.mean(out[inside] ** 2))) if inside.any() else 1.0
    return out / max(rms, 1e-12)
