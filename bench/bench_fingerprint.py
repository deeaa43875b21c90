"""Fingerprints of simulated fingers through the pipeline, judged by NIST NBIS.

Captures: ``IDENTITIES`` synthetic fingers (``FingertipShape.identity`` 0..19) x
``CAPTURES`` poses each, drawn per capture from a seeded generator: roll, yaw, pitch uniform
in +-``ROLL_DEG``, +-``YAW_DEG``, +-``PITCH_DEG``, the apex shifted by up to +-``SHIFT_MM``
in x and y (working distance unchanged). Each pose is a new ``SimulatedRig``; its burst is
one ``rig.render(Scene.FINGER, [k], rng=...)`` per LED, with sensor noise, as the driver
renders it.

Reconstruction: ``pipeline.reconstruct_prepared`` with ``ReconstructionOptions(model=...,
enhance=True)``, HK and Lambertian, as recon_node runs it
(``burst_reconstruction.reconstruct_burst``)
with a calibration prepared once (``prepare_calibration``) from the rig's TRUE LED positions
(``rig.led_positions_optical``: the near-light model), the true apex directions
(``rig.light_directions_ps()``, checked only when LED positions are given) and the flat field
of the rig's white target (7 noisy renders and a dark one, ``flat_field_maps``: portions and
relative intensities), all from the unshifted default rig, so a shifted finger is
reconstructed with a fixed calibration, as in service. Then ``rolled_print`` (defaults:
normals' Laplacian, no Gabor); a print it refuses counts as a failed capture (its genuine
scores 0).

Figures per model (``fingerprint.<model>.*``):

- geometric fidelity: every print pixel's source pixel (``source_x/y``) carries the true
  rolled-plane position of the skin it sees (``FingerTruth.rolled_mm``, bilinear); a
  similarity transform print mm -> rolled mm (rotation, isotropic scale, shift; no
  reflection, Umeyama 1991) is fitted by least squares: ``scale_err_pct_*`` = 100 |s - 1|
  (median, max; target median <= 0.5 %), ``residual_mm_median`` the median distance left. An
  unconstrained affine fit with a negative determinant would mean a mirrored print:
  ``mirrored_prints`` counts them (0 expected);
- scale per region: the TRUE rolled plane cut into cells of ``REGION_MM`` (4 mm) square
  (from the pattern grid's corner); the print pixels showing a cell's skin, when they cover
  at least ``REGION_MIN_FILL`` (half) of it, are fitted alone by the same similarity, giving
  the cell's scale s_c. ``scale_err_pct_region_abs_max`` / ``_abs_p95``: 100 |s_c - 1|,
  worst cell of all the prints / 95th percentile over them. That holds the unrolling's own
  local strain: a fingertip's doubly curved cap has no isometric map to a plane. The print's
  plane is the rolled finger's (``surface.rolled_layout``: arc lengths around and along
  the finger, the generator's own definition of its rolled plane), within ~1.6 % of it
  everywhere for the TRUE surface (``fingerprint.truth_surface.scale_err_pct_region_max``,
  capture 0 of each finger; with the springs layout, ``RolledPrintOptions.layout``, ~6 % at
  the print's edge cells: a different map of the cap). So the reconstruction's own share is
  judged too (target <= 1 %):
  ``scale_err_pct_region_max`` / ``_p95``: 100 |s_c / t_c - 1|, with t_c the same cell's
  scale on the print of the TRUE surface of the same capture (``true_surface_cells``),
  worst cell / 95th percentile; ``regions`` the cells compared;
- minutiae: mindtct's minutiae on the print, each taken to the true rolled position of its
  pixel, against the generator's ground truth within ``MATCH_MM`` (0.3 mm). Evaluated: the
  print less ``BORDER_MM`` (1 mm) along its outline, and the generator's area where it keeps
  ground truth (its print less 1 mm, 1.5 mm from singular points). ``recall`` = evaluated
  ground truth with a detection within 0.3 mm, ``precision`` = evaluated detections with a
  ground truth within 0.3 mm (pooled over the captures; target >= 95 % each);
  ``minutia_err_mm_median``: matched pairs, the detection through the fitted similarity vs
  its ground truth (detection error and the unrolling's distortion together);
- ``nfiq2_median``, ``nfiq2_p10`` (target median >= 55);
- bozorth3: genuine = capture vs capture of one finger (3 pairs a finger) and capture vs
  the finger's ground-truth rolled print (``rig.rolled_print()``); impostor = every capture
  vs every capture of another finger (1710) and vs every other finger's ground truth (1140).
  ``genuine_min``
  (both kinds) vs ``impostor_max`` (target: every genuine above every impostor); ``eer_pct``
  and ``fnmr_at_fmr1_pct`` over all genuine and impostor scores;
- ``print_ms_median``: ``rolled_print``'s ``timings_ms['total']`` per burst;
- ``fingerprint.generate_s.median``: ``generate_fingerprint`` of one whorl (20 x 25 mm at
  500 ppi), median of ``GENERATIONS`` runs;
- diagnosis of the scale: ``fingerprint.truth_surface.scale_err_pct_median``, the same fit
  for prints of the rig's TRUE depth and normals (capture 0 of each finger: the unrolling's
  own share; ``...truth_surface.scale_err_pct_region_max`` its worst region), and
  ``margin_sag_ratio``, the reconstructed depth's sag below the apex over
  the true one where the finger is tilted more than 40 deg (< 1: flatter).

Contact-print arm (``fingerprint_contact_arm``; issue 23, item 2): per finger ``CONTACTS``
(3) plate impressions of a 500 ppi scanner (``simulation.contact_impression``: Hertzian
contact ellipse, the plastic distortion of Cappelli, Maio & Maltoni, ICAPR 2001, the
scanner's look and a random placement); ``fingerprint.<model>.contact.genuine_3d_median``
(each 3D capture vs each impression of its finger) beside
``fingerprint.contact.genuine_cc_median`` (impression vs impression of one finger):
``fingerprint.<model>.contact.ratio`` target >= 0.8; impostors (3D vs other fingers'
impressions, impression vs impression) median and max, target unchanged (not 25 % above
contact-vs-contact); ``eer_pct`` and ``fnmr_at_fmr01_pct`` (FMR <= 0.1 %; 3420 and 1710
impostor scores) of both; the ground-truth rolled print vs the impressions as the diagnosis.

Records and print quality (``fingerprint_records``; issue 23, items 3 and 4): every HK
print's WSQ image, ISO/IEC 19794-2 record and ANSI/NIST-ITL transaction made and read back
by independent readers (``fingerprint.records.checked`` / ``read_back``, target: all; the
time to make them, ``ms_median``); per model, what a Scan ``min_nfiq2`` of 20, 30, 40, 50
would do: ``nfiq2_<t>.rejected_pct`` of the captures and ``nfiq2_<t>.fnmr_at_fmr01_pct``,
the FNMR at FMR 0.1 % with a rejected capture's genuine comparisons counted as non-matches.

``fingerprint.truth.nfiq2_median`` is the ground-truth prints' own quality. Each figure
that misses its target is named in the printed output with the gap and the likely cause.

Run: ``python bench/bench_fingerprint.py`` (~5 min on the 2-core machine); ``run()`` returns
the figures for bench/run_all.py. Needs ``nbis-py`` (requirements.txt).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))

from check_fingerprint_pattern import (
    compare_minutiae,
    nbis_extractor,
    png_bytes,
    truth_keeps,
)
from figures_report import print_figures
from fingerprint_contact_arm import contact_table, run_arm
from fingerprint_records import RecordsCheck, nfiq2_threshold_effect, records_table

from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_driver.simulation import FingertipShape, RigConfig, Scene, SimulatedRig
from fingerps_driver.simulation.fingerprint_orientation import PatternClass
from fingerps_driver.simulation.fingerprint_pattern import (
    FingerprintPattern,
    generate_fingerprint,
)
from fingerps_recon.errors import RolledPrintError
from fingerps_recon.photometric.pipeline import (
    Model,
    PreparedCalibration,
    Reconstruction,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.surface.rolled_print import RolledPrint, rolled_print

IDENTITIES = 20
CAPTURES = 3
ROLL_DEG, YAW_DEG, PITCH_DEG, SHIFT_MM = 5.0, 10.0, 5.0, 1.0
MATCH_MM = 0.3
BORDER_MM = 1.0
SINGULAR_ZONE_MM = 1.5
MARGIN_TILT_DEG = 40.0
GENERATIONS = 3
MODELS = (Model.HK, Model.LAMBERT)
SEED = 12
REGION_MM = 4.0
REGION_MIN_FILL = 0.5
TARGETS = {"scale_err_pct_median": 0.5, "scale_err_pct_region_max": 1.0, "recall": 0.95,
           "precision": 0.95, "nfiq2_median": 55}


@dataclass(frozen=True)
class Pose:
    roll_deg: float
    yaw_deg: float
    pitch_deg: float
    shift_mm: tuple[float, float]


@dataclass
class PrintResult:
    """One capture's print under one model, and what was measured on it."""

    template: object | None = None
    nfiq2: float = float("nan")
    scale: float = float("nan")
    residual_mm: float = float("nan")
    mirrored: bool = False
    gt_evaluated: int = 0
    gt_found: int = 0
    det_evaluated: int = 0
    det_true: int = 0
    minutia_err_mm: list[float] = field(default_factory=list)
    print_ms: float = float("nan")
    sag_ratio: float = float("nan")
    cells: dict[tuple[int, int], float] = field(default_factory=dict)
    truth_cells: dict[tuple[int, int], float] = field(default_factory=dict)
    error: str = ""


def draw_pose(identity: int, capture: int) -> Pose:
    """The pose of one capture: uniform within the module's ranges, seeded."""
    rng = np.random.default_rng(np.random.SeedSequence([SEED, identity, capture]))
    roll, yaw, pitch = rng.uniform(-1.0, 1.0, 3) * (ROLL_DEG, YAW_DEG, PITCH_DEG)
    shift = rng.uniform(-SHIFT_MM, SHIFT_MM, 2)
    return Pose(float(roll), float(yaw), float(pitch), (float(shift[0]), float(shift[1])))


def posed_rig(identity: int, pose: Pose) -> SimulatedRig:
    x, y, z = FingertipShape().apex_optical_m
    return SimulatedRig(RigConfig(finger=FingertipShape(
        identity=identity, roll_deg=pose.roll_deg, yaw_deg=pose.yaw_deg,
        pitch_deg=pose.pitch_deg,
        apex_optical_m=(x + 1e-3 * pose.shift_mm[0], y + 1e-3 * pose.shift_mm[1], z))))


def calibrations() -> dict[Model, PreparedCalibration]:
    """The prepared calibration per model (module docstring: true LEDs, white target)."""
    rig = SimulatedRig()
    white = rig.render_burst(Scene.WHITE_TARGET, seed=200)
    dark = rig.render(Scene.WHITE_TARGET, [], rng=np.random.default_rng(199))
    flat = flat_field_maps(white, dark=dark)
    return {model: prepare_calibration(
        rig.light_directions_ps(), camera_matrix=rig.camera_matrix, shape=white.shape[1:],
        intensities=flat.relative_intensities, portions=flat.portions,
        led_positions_optical=rig.led_positions_optical,
        options=ReconstructionOptions(model=model, enhance=True)) for model in MODELS}


def reconstructed_print(rig: SimulatedRig, images: np.ndarray, prepared: PreparedCalibration,
                        model: Model) -> tuple[Reconstruction, RolledPrint]:
    """A burst reconstructed as recon_node does (ridge transform on) and its rolled print;
    raises ``RolledPrintError`` when the print cannot be made."""
    recon = reconstruct_prepared(images, prepared, full_scale=rig.max_value(),
                                 options=ReconstructionOptions(model=model, enhance=True))
    return recon, rolled_print(recon.depth_m, mask=recon.mask, camera_matrix=rig.camera_matrix,
                               normals_ps=recon.normals_ps)


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst ~ s R src + t, no reflection (Umeyama, IEEE TPAMI 13(4),
    1991): (s, R (2, 2), t (2,)) of point sets (N, 2)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    u, sv, vt = np.linalg.svd(b.T @ a / len(a))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sv) @ d) / (a * a).sum(axis=1).mean())
    return scale, rot, md - scale * rot @ ms


def true_rolled_at_print(result: RolledPrint, rolled_mm: np.ndarray) -> np.ndarray:
    """(Ho, Wo, 2) true rolled-plane mm of the skin each print pixel shows; NaN off it."""
    out = np.full((*result.mask.shape, 2), np.nan, dtype=np.float32)
    sx = np.where(result.mask, result.source_x, -1e4).astype(np.float32)
    sy = np.where(result.mask, result.source_y, -1e4).astype(np.float32)
    for c in range(2):
        out[..., c] = cv2.remap(np.ascontiguousarray(rolled_mm[..., c]), sx, sy,
                                cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=np.nan)
    out[~result.mask] = np.nan
    return out


def print_scale(result: RolledPrint, rolled_mm: np.ndarray) -> tuple[float, np.ndarray,
                                                                        np.ndarray]:
    """The similarity print mm -> true rolled mm (``similarity``) fitted over the print."""
    truth = true_rolled_at_print(result, rolled_mm)
    known = np.isfinite(truth).all(axis=-1)
    rows, cols = np.nonzero(known)
    print_mm = np.stack([result.origin_mm[0] + cols / result.px_per_mm,
                         result.origin_mm[1] + rows / result.px_per_mm], axis=1)
    return similarity(print_mm, truth[known].astype(np.float64))


def true_surface_scale(rig: SimulatedRig, truth) -> float:
    """Scale s of the print of the rig's TRUE surface (depth and normals): the unrolling's
    own share of the scale error."""
    fp = rolled_print(truth.depth_m, mask=truth.mask, camera_matrix=rig.camera_matrix,
                      normals_ps=truth.normals_ps)
    return print_scale(fp, truth.rolled_mm)[0]


def region_scales(print_mm: np.ndarray, true_mm: np.ndarray, ppmm: float
                  ) -> dict[tuple[int, int], float]:
    """Scale s of the similarity (``similarity``) print mm (N, 2) -> true rolled mm (N, 2)
    fitted per ``REGION_MM`` cell of the true rolled plane whose print pixels cover at
    least ``REGION_MIN_FILL`` of it: {(cell x, cell y): s}."""
    cell = np.floor(true_mm / REGION_MM).astype(np.int64)
    keys, inverse, counts = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    order = np.argsort(inverse.reshape(-1), kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    enough = REGION_MIN_FILL * (REGION_MM * ppmm) ** 2
    return {(int(keys[i, 0]), int(keys[i, 1])):
            similarity(print_mm[idx], true_mm[idx])[0]
            for i in range(len(keys)) if counts[i] >= enough
            for idx in [order[starts[i]:starts[i + 1]]]}


def true_surface_cells(rig: SimulatedRig, truth) -> dict[tuple[int, int], float]:
    """``region_scales`` of the print of the rig's TRUE surface (depth and normals)."""
    fp = rolled_print(truth.depth_m, mask=truth.mask, camera_matrix=rig.camera_matrix,
                      normals_ps=truth.normals_ps)
    known_truth = true_rolled_at_print(fp, truth.rolled_mm)
    known = np.isfinite(known_truth).all(axis=-1)
    rows, cols = np.nonzero(known)
    print_mm = np.stack([fp.origin_mm[0] + cols / fp.px_per_mm,
                         fp.origin_mm[1] + rows / fp.px_per_mm], axis=1)
    return region_scales(print_mm, known_truth[known].astype(np.float64), fp.px_per_mm)


def margin_sag_ratio(depth_m: np.ndarray, mask: np.ndarray, truth) -> float:
    """Median ratio of the reconstructed to the true sag (depth below the apex, the true
    surface's nearest pixel) where the true surface is tilted more than
    ``MARGIN_TILT_DEG``: < 1 when the reconstructed shape is flatter than the finger."""
    both = mask & truth.mask & np.isfinite(depth_m)
    if not both.any():
        return float("nan")
    true_depth = np.where(both, truth.depth_m, np.inf)
    apex = np.unravel_index(int(np.argmin(true_depth)), true_depth.shape)
    tilt = np.degrees(np.arccos(np.clip(truth.normals_ps[..., 2], -1.0, 1.0)))
    steep = both & (tilt > MARGIN_TILT_DEG)
    sag = (depth_m - depth_m[apex])[steep] / (truth.depth_m - truth.depth_m[apex])[steep]
    return float(np.median(sag)) if steep.any() else float("nan")


def measure(result: RolledPrint, rolled_mm: np.ndarray, pattern: FingerprintPattern,
            template, out: PrintResult) -> None:
    """Geometric fidelity and minutiae of one print (module docstring) into ``out``."""
    ppmm = result.px_per_mm
    truth = true_rolled_at_print(result, rolled_mm)
    known = np.isfinite(truth).all(axis=-1)
    rows, cols = np.nonzero(known)
    print_mm = np.stack([result.origin_mm[0] + cols / ppmm,
                         result.origin_mm[1] + rows / ppmm], axis=1)
    dst = truth[known].astype(np.float64)
    scale, rot, shift = similarity(print_mm, dst)
    out.scale = scale
    out.residual_mm = float(np.median(np.linalg.norm(
        print_mm @ (scale * rot).T + shift - dst, axis=1)))
    affine = np.linalg.lstsq(np.c_[print_mm, np.ones(len(print_mm))], dst, rcond=None)[0]
    out.mirrored = bool(np.linalg.det(affine[:2]) < 0.0)
    out.cells = region_scales(print_mm, dst, ppmm)

    # Where the print can be judged: its mask less BORDER_MM along the outline.
    inner = ndimage.distance_transform_edt(np.pad(known, 1))[1:-1, 1:-1] / ppmm > BORDER_MM
    gt = np.array([(m.x_mm, m.y_mm) for m in pattern.minutiae]).reshape(-1, 2)
    # Ground truth into the print: the print pixel showing the nearest skin.
    dist, nearest = cKDTree(dst).query(gt)
    gt_in = (dist < 2.0 / ppmm) & inner[rows[nearest], cols[nearest]]
    det = np.array([(m.x(), m.y()) for m in template.get()], dtype=int).reshape(-1, 2)
    det = det[(det[:, 0] >= 0) & (det[:, 0] < known.shape[1])
              & (det[:, 1] >= 0) & (det[:, 1] < known.shape[0])]
    det_known = known[det[:, 1], det[:, 0]]
    det = det[det_known]
    det_true = truth[det[:, 1], det[:, 0]].astype(np.float64)
    det_in = inner[det[:, 1], det[:, 0]] & truth_keeps(
        pattern, det_true, border_mm=BORDER_MM, singular_zone_mm=SINGULAR_ZONE_MM)
    if len(det) and len(gt):
        d = np.hypot(gt[:, None, 0] - det_true[None, :, 0], gt[:, None, 1] - det_true[None, :, 1])
        found = d.min(axis=1) <= MATCH_MM
        out.gt_evaluated = int(gt_in.sum())
        out.gt_found = int((found & gt_in).sum())
        out.det_evaluated = int(det_in.sum())
        out.det_true = int((d.min(axis=0) <= MATCH_MM)[det_in].sum())
        pairs = np.flatnonzero(found & gt_in)
        det_mm = np.stack([result.origin_mm[0] + det[:, 0] / ppmm,
                           result.origin_mm[1] + det[:, 1] / ppmm], axis=1)
        registered = det_mm @ (scale * rot).T + shift
        best = d[pairs].argmin(axis=1)
        out.minutia_err_mm = np.linalg.norm(registered[best] - gt[pairs], axis=1).tolist()
    else:
        out.gt_evaluated = int(gt_in.sum())
        out.det_evaluated = int(det_in.sum())


def error_rates(genuine: np.ndarray, impostor: np.ndarray, *,
                fmr_max: float = 0.01) -> tuple[float, float]:
    """(EER, FNMR at FMR <= ``fmr_max``), fractions; a score >= the threshold is a match."""
    thresholds = np.unique(np.concatenate([genuine, impostor, [np.inf]]))
    fmr = (impostor[None, :] >= thresholds[:, None]).mean(axis=1)
    fnmr = (genuine[None, :] < thresholds[:, None]).mean(axis=1)
    i = int(np.argmin(np.abs(fmr - fnmr)))
    gap = fnmr - fmr  # rises with the threshold
    j = int(np.searchsorted(gap, 0.0))
    if 0 < j < len(gap) and gap[j] != gap[j - 1]:  # interpolate the crossing
        w = -gap[j - 1] / (gap[j] - gap[j - 1])
        eer = float((1 - w) * (fmr[j - 1] + fnmr[j - 1]) / 2 + w * (fmr[j] + fnmr[j]) / 2)
    else:
        eer = float((fmr[i] + fnmr[i]) / 2)
    ok = fmr <= fmr_max
    return eer, float(fnmr[ok].min()) if ok.any() else 1.0


def generation_s() -> float:
    """Median seconds of ``generate_fingerprint`` of one whorl over ``GENERATIONS`` runs."""
    times = []
    for seed in range(GENERATIONS):
        t0 = time.perf_counter()
        generate_fingerprint(3 + seed, pattern_class=PatternClass.WHORL)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run() -> dict[str, float]:
    """Run the benchmark, print its table, return the ``fingerprint.*`` figures."""
    t_start = time.perf_counter()
    extractor = nbis_extractor()
    prepared = calibrations()
    results: dict[Model, list[list[PrintResult]]] = {m: [] for m in MODELS}
    truth_templates, truth_nfiq2, truth_minutiae = [], [], []
    surface_scales: list[float] = []
    surface_regions: list[float] = []  # 100 |t_c - 1| of the true surfaces' cells
    fingers: list[str] = []  # class and ground-truth minutiae of each finger
    records = RecordsCheck()  # the HK prints' records, read back
    print(f"{IDENTITIES} fingers x {CAPTURES} captures; poses roll +-{ROLL_DEG:g}, yaw "
          f"+-{YAW_DEG:g}, pitch +-{PITCH_DEG:g} deg, shift +-{SHIFT_MM:g} mm", flush=True)
    print(f"{'id':>3} {'c':>1} {'roll':>5} {'yaw':>5} {'pitch':>5} {'dx':>5} {'dy':>5} "
          f"{'rig s':>5} | " + " | ".join(
              f"{m.value[:3]} {'scale%':>6} {'rec':>4} {'prec':>4} {'nfiq':>4} {'ms':>4}"
              for m in MODELS), flush=True)
    for identity in range(IDENTITIES):
        for model in MODELS:
            results[model].append([])
        for capture in range(CAPTURES):
            pose = draw_pose(identity, capture)
            t0 = time.perf_counter()
            rig = posed_rig(identity, pose)
            images = rig.render_burst(Scene.FINGER, seed=[SEED, identity, capture])
            truth = rig.finger_truth()
            rolled_mm = truth.rolled_mm
            pattern = rig.fingerprint
            if capture == 0:
                surface_scales.append(abs(true_surface_scale(rig, truth) - 1.0))
                card = extractor.extract_minutiae(png_bytes(rig.rolled_print()))
                truth_templates.append(card)
                truth_nfiq2.append(float(card.quality().score))
                truth_minutiae.append(compare_minutiae(pattern, card.get()))
                fingers.append(f"{pattern.pattern_class.value}, {len(pattern.minutiae)} "
                               "minutiae")
            truth_cells = true_surface_cells(rig, truth)
            if capture == 0:
                surface_regions += [100 * abs(t - 1) for t in truth_cells.values()]
            rig_s = time.perf_counter() - t0
            cells = []
            for model in MODELS:
                out = PrintResult(truth_cells=truth_cells)
                try:
                    recon, fp = reconstructed_print(rig, images, prepared[model], model)
                except RolledPrintError as error:
                    out.error = f"{error.reason.value}: {error}"
                    cells.append(f"{model.value[:3]} refused: {error.reason.value}")
                else:
                    out.print_ms = fp.timings_ms["total"]
                    out.sag_ratio = margin_sag_ratio(recon.depth_m, recon.mask, truth)
                    out.template = extractor.extract_minutiae(png_bytes(fp.image))
                    out.nfiq2 = float(out.template.quality().score)
                    measure(fp, rolled_mm, pattern, out.template, out)
                    if model is Model.HK:
                        records.check(fp.image, f"{identity}.{capture}")
                    rec = out.gt_found / max(out.gt_evaluated, 1)
                    prec = out.det_true / max(out.det_evaluated, 1)
                    cells.append(f"{model.value[:3]} {100 * (out.scale - 1):+6.2f} "
                                 f"{rec:4.2f} {prec:4.2f} {out.nfiq2:4.0f} "
                                 f"{out.print_ms:4.0f}")
                results[model][identity].append(out)
            print(f"{identity:>3} {capture:>1} {pose.roll_deg:+5.1f} {pose.yaw_deg:+5.1f} "
                  f"{pose.pitch_deg:+5.1f} {pose.shift_mm[0]:+5.2f} {pose.shift_mm[1]:+5.2f} "
                  f"{rig_s:5.1f} | " + " | ".join(cells), flush=True)
            del rig, images

    print(f"bozorth3 comparisons ... ({time.perf_counter() - t_start:.0f} s so far)",
          flush=True)
    figures: dict[str, float] = {}
    for model in MODELS:
        figures.update(_scores(model, results[model], truth_templates, fingers))
    figures["fingerprint.truth.nfiq2_median"] = float(np.median(truth_nfiq2))
    figures["fingerprint.truth_surface.scale_err_pct_median"] = float(
        100 * np.median(surface_scales))
    figures["fingerprint.truth_surface.scale_err_pct_region_max"] = float(
        np.max(surface_regions))
    for key in ("recall", "precision"):
        figures[f"fingerprint.truth.{key}_median"] = float(
            np.median([t[key] for t in truth_minutiae]))
    figures["fingerprint.identities"] = float(IDENTITIES)
    figures["fingerprint.captures"] = float(IDENTITIES * CAPTURES)
    figures["fingerprint.generate_s.median"] = generation_s()
    figures.update(records.figures())
    figures.update(run_arm(extractor, {m.value: [[r.template for r in c] for c in results[m]]
                                       for m in MODELS}, truth_templates, error_rates))
    figures["fingerprint.seconds"] = time.perf_counter() - t_start
    _table(figures)
    contact_table(figures, [m.value for m in MODELS])
    records_table(figures, [m.value for m in MODELS], records.failures)
    return figures


def run_print_timing() -> dict[str, float]:
    """``fingerprint.<model>.print_ms_median`` alone: the same captures as :func:`run`,
    reconstructed and printed, without NBIS (the AVX2 pass of bench/run_all.py)."""
    prepared = calibrations()
    times: dict[Model, list[float]] = {m: [] for m in MODELS}
    for identity in range(IDENTITIES):
        for capture in range(CAPTURES):
            rig = posed_rig(identity, draw_pose(identity, capture))
            images = rig.render_burst(Scene.FINGER, seed=[SEED, identity, capture])
            for model in MODELS:
                try:
                    _, fp = reconstructed_print(rig, images, prepared[model], model)
                except RolledPrintError:
                    continue
                times[model].append(fp.timings_ms["total"])
    return {f"fingerprint.{m.value}.print_ms_median":
            float(np.median(times[m])) if times[m] else float("nan") for m in MODELS}


def _score(a: PrintResult, b) -> float:
    """bozorth3 score of a capture's print against a template (0 if it has no print)."""
    if a.template is None or b is None:
        return 0.0
    return float(a.template.compare(b))


def _scores(model: Model, per_id: list[list[PrintResult]],
            truth_templates: list, fingers: list[str]) -> dict[str, float]:
    """The figures of one model (module docstring)."""
    flat = [r for captures in per_id for r in captures]
    printed = [r for r in flat if r.template is not None]
    # (score, who): "i.c" is finger i's capture c, "i.T" its ground-truth print.
    genuine_cc = [(_score(c[a], c[b].template), f"{i}.{a} v {i}.{b}")
                  for i, c in enumerate(per_id)
                  for a in range(len(c)) for b in range(a + 1, len(c))]
    genuine_gt = [(_score(r, truth_templates[i]), f"{i}.{a} v {i}.T")
                  for i, c in enumerate(per_id) for a, r in enumerate(c)]
    impostor = []
    for i, ci in enumerate(per_id):
        for j, cj in enumerate(per_id):
            if j == i:
                continue
            impostor += [(_score(r, truth_templates[j]), f"{i}.{a} v {j}.T")
                         for a, r in enumerate(ci)]
            if j > i:
                impostor += [(_score(r, cj[b].template), f"{i}.{a} v {j}.{b}")
                             for a, r in enumerate(ci) for b in range(len(cj))]
    lowest = min(genuine_cc + genuine_gt)
    highest = max(impostor)
    thresholds = nfiq2_threshold_effect(
        f"fingerprint.{model.value}.",
        {f"{i}.{a}": r.nfiq2 for i, c in enumerate(per_id) for a, r in enumerate(c)},
        genuine_cc + genuine_gt, impostor, error_rates)

    def who(label: str) -> str:
        a, b = (int(side.split(".")[0]) for side in label.split(" v "))
        return f"{label}: {fingers[a]}" + ("" if a == b else f" / {fingers[b]}")

    print(f"{model.value}: {len(genuine_cc) + len(genuine_gt)} genuine, {len(impostor)} "
          f"impostor comparisons; lowest genuine {lowest[0]:.0f} ({who(lowest[1])}), "
          f"highest impostor {highest[0]:.0f} ({who(highest[1])}); i.c = finger i's capture "
          "c, i.T its ground-truth print", flush=True)
    genuine_cc = [g for g, _ in genuine_cc]
    genuine_gt = [g for g, _ in genuine_gt]
    genuine = np.array(genuine_cc + genuine_gt)
    impostor = np.array([g for g, _ in impostor])
    eer, fnmr = error_rates(genuine, impostor)
    scale_err = 100 * np.abs(np.array([r.scale for r in printed]) - 1.0)
    cells_abs = np.array([100 * abs(v - 1) for r in printed for v in r.cells.values()])
    regions = np.array([100 * abs(v / r.truth_cells[c] - 1) for r in printed
                        for c, v in r.cells.items() if c in r.truth_cells])
    errors = [e for r in printed for e in r.minutia_err_mm]
    nfiq2 = np.array([r.nfiq2 for r in printed])
    p = f"fingerprint.{model.value}."
    return {
        p + "prints": float(len(printed)),
        p + "prints_refused": float(len(flat) - len(printed)),
        p + "mirrored_prints": float(sum(r.mirrored for r in printed)),
        p + "scale_err_pct_median": float(np.median(scale_err)),
        p + "scale_err_pct_max": float(np.max(scale_err)),
        p + "scale_pct_mean": float(100 * (np.mean([r.scale for r in printed]) - 1.0)),
        p + "scale_err_pct_region_max": float(np.max(regions)),
        p + "scale_err_pct_region_p95": float(np.percentile(regions, 95)),
        p + "regions": float(len(regions)),
        p + "scale_err_pct_region_abs_max": float(np.max(cells_abs)),
        p + "scale_err_pct_region_abs_p95": float(np.percentile(cells_abs, 95)),
        p + "residual_mm_median": float(np.median([r.residual_mm for r in printed])),
        p + "minutia_err_mm_median": float(np.median(errors)) if errors else float("nan"),
        p + "recall": sum(r.gt_found for r in printed) / max(
            sum(r.gt_evaluated for r in printed), 1),
        p + "precision": sum(r.det_true for r in printed) / max(
            sum(r.det_evaluated for r in printed), 1),
        p + "truth_minutiae_evaluated": float(sum(r.gt_evaluated for r in printed)),
        p + "nfiq2_median": float(np.median(nfiq2)),
        p + "nfiq2_p10": float(np.percentile(nfiq2, 10)),
        p + "genuine_cc_min": float(np.min(genuine_cc)),
        p + "genuine_cc_median": float(np.median(genuine_cc)),
        p + "genuine_truth_min": float(np.min(genuine_gt)),
        p + "genuine_truth_median": float(np.median(genuine_gt)),
        p + "impostor_max": float(np.max(impostor)),
        p + "impostor_median": float(np.median(impostor)),
        p + "eer_pct": 100 * eer,
        p + "fnmr_at_fmr1_pct": 100 * fnmr,
        p + "print_ms_median": float(np.nanmedian([r.print_ms for r in printed])),
        p + "margin_sag_ratio": float(np.nanmedian([r.sag_ratio for r in printed])),
        **thresholds,
    }


def _table(f: dict[str, float]) -> None:
    """The summary table and the verdict on each target."""
    rows = [
        ("prints made / refused", "prints", "prints_refused", "{:.0f} / {:.0f}"),
        ("mirrored registrations", "mirrored_prints", None, "{:.0f}"),
        ("scale error % median / max", "scale_err_pct_median", "scale_err_pct_max",
         "{:.2f} / {:.2f}"),
        ("mean scale - 1, %", "scale_pct_mean", None, "{:+.2f}"),
        (f"scale error % per {REGION_MM:g} mm region p95 / max", "scale_err_pct_region_p95",
         "scale_err_pct_region_max", "{:.2f} / {:.2f}"),
        ("  (the same, absolute: unrolling included)", "scale_err_pct_region_abs_p95",
         "scale_err_pct_region_abs_max", "{:.2f} / {:.2f}"),
        ("registration residual mm (median)", "residual_mm_median", None, "{:.3f}"),
        ("minutia position error mm (median)", "minutia_err_mm_median", None, "{:.3f}"),
        ("minutiae recall / precision", "recall", "precision", "{:.3f} / {:.3f}"),
        ("NFIQ 2 median / p10", "nfiq2_median", "nfiq2_p10", "{:.0f} / {:.0f}"),
        ("genuine capture-capture min / median", "genuine_cc_min", "genuine_cc_median",
         "{:.0f} / {:.0f}"),
        ("genuine capture-truth min / median", "genuine_truth_min", "genuine_truth_median",
         "{:.0f} / {:.0f}"),
        ("impostor max / median", "impostor_max", "impostor_median", "{:.0f} / {:.0f}"),
        ("EER % / FNMR % at FMR 1 %", "eer_pct", "fnmr_at_fmr1_pct", "{:.2f} / {:.2f}"),
        ("rolled_print ms per burst (median)", "print_ms_median", None, "{:.0f}"),
        (f"depth sag / true (tilt > {MARGIN_TILT_DEG:.0f} deg)", "margin_sag_ratio", None,
         "{:.3f}"),
    ]
    print(f"\n{'':<38}" + "".join(f"{m.value:>16}" for m in MODELS))
    for label, a, b, fmt in rows:
        cells = []
        for m in MODELS:
            p = f"fingerprint.{m.value}."
            values = [f[p + a]] + ([f[p + b]] if b else [])
            cells.append(fmt.format(*values))
        print(f"{label:<38}" + "".join(f"{c:>16}" for c in cells))
    print(f"ground-truth prints (rig.rolled_print()): NFIQ 2 median "
          f"{f['fingerprint.truth.nfiq2_median']:.0f}, mindtct recall / precision median "
          f"{f['fingerprint.truth.recall_median']:.2f} / "
          f"{f['fingerprint.truth.precision_median']:.2f}; prints of the true surfaces: "
          f"scale error median {f['fingerprint.truth_surface.scale_err_pct_median']:.2f} %, "
          f"worst region {f['fingerprint.truth_surface.scale_err_pct_region_max']:.2f} %; "
          f"one finger generated in {f['fingerprint.generate_s.median']:.2f} s (median); "
          f"{f['fingerprint.seconds']:.0f} s in all")
    for m in MODELS:
        p = f"fingerprint.{m.value}."
        misses = []
        if f[p + "scale_err_pct_median"] > TARGETS["scale_err_pct_median"]:
            misses.append(
                f"scale error {f[p + 'scale_err_pct_median']:.2f} % > "
                f"{TARGETS['scale_err_pct_median']:g} % (by "
                f"{f[p + 'scale_err_pct_median'] - TARGETS['scale_err_pct_median']:.2f} "
                "points; the print comes out "
                f"{f[p + 'scale_pct_mean']:.1f} % small): the prints of the TRUE surfaces "
                f"are within {f['fingerprint.truth_surface.scale_err_pct_median']:.2f} % (the "
                "unrolling's share), so the rest is the reconstructed depth (the integrated "
                "normals), flatter than the finger: its sag where the finger is tilted more "
                f"than {MARGIN_TILT_DEG:.0f} deg is {f[p + 'margin_sag_ratio']:.3f} of the "
                "true one, so its arcs are shorter (and the normals are as flat there: "
                "unrolling from their slopes instead of the depth gives the same scale)")
        if f[p + "scale_err_pct_region_max"] > TARGETS["scale_err_pct_region_max"]:
            misses.append(
                f"worst region's scale error {f[p + 'scale_err_pct_region_max']:.2f} % > "
                f"{TARGETS['scale_err_pct_region_max']:g} % (p95 "
                f"{f[p + 'scale_err_pct_region_p95']:.2f} %; against the true rolled plane "
                f"itself {f[p + 'scale_err_pct_region_abs_max']:.2f} %, the true surfaces' "
                f"own {f['fingerprint.truth_surface.scale_err_pct_region_max']:.2f} %)")
        for key in ("recall", "precision"):
            if f[p + key] < TARGETS[key]:
                misses.append(
                    f"{key} {100 * f[p + key]:.1f} % < {100 * TARGETS[key]:.0f} % (short by "
                    f"{100 * (TARGETS[key] - f[p + key]):.1f} points; mindtct on the "
                    "ground-truth prints themselves: "
                    f"{100 * f[f'fingerprint.truth.{key}_median']:.0f} %)")
        if f[p + "nfiq2_median"] < TARGETS["nfiq2_median"]:
            misses.append(f"NFIQ 2 median {f[p + 'nfiq2_median']:.0f} < "
                          f"{TARGETS['nfiq2_median']} (the ground-truth "
                          f"prints: {f['fingerprint.truth.nfiq2_median']:.0f})")
        genuine_min = min(f[p + "genuine_cc_min"], f[p + "genuine_truth_min"])
        if genuine_min <= f[p + "impostor_max"]:
            misses.append(f"lowest genuine {genuine_min:.0f} <= highest impostor "
                          f"{f[p + 'impostor_max']:.0f} (bozorth3's score grows with the "
                          "minutiae it pairs: the fingers, classes and minutiae counts of "
                          "both comparisons are printed above)")
        print(f"{m.value}: " + ("every target met" if not misses else
                                "MISSED: " + "; ".join(misses)))


if __name__ == "__main__":
    print_figures(run())
