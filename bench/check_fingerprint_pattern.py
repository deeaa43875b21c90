"""NIST NBIS as the judge of the synthetic fingerprints (not in make bench).

For a few identities (seeds; the class drawn from the seed): the generator's time, its
ground-truth minutiae, and on the 500 ppi render

- mindtct minutiae (through ``nbis-py``) against the ground truth: recall = fraction of
  ground-truth minutiae with a detected one within 0.3 mm; precision = fraction of the
  detections inside the evaluated area (the print less ``border_mm`` at its edge and
  ``singular_zone_mm`` about singular points, where the ground truth is not kept) with a
  ground-truth minutia within 0.3 mm; and the median angle difference of matched pairs;
- bozorth3 scores: genuine = the render against itself shifted by (0.6, -0.4) mm and rotated
  by 4 degrees; impostor = against the next identity's render;
- NFIQ 2 score of the render.

Usage (tools/ros_env.sh sourced): ``python bench/check_fingerprint_pattern.py [--seeds N]``.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from scipy import ndimage

from fingerps_driver.simulation.fingerprint_pattern import (
    FingerprintPattern,
    generate_fingerprint,
    render_rolled_print,
)

MATCH_RADIUS_MM = 0.3
PX_PER_MM = 500 / 25.4


def nbis_extractor():  # nbis-py is optional: imported here only
    import nbis

    settings = nbis.NbisExtractorSettings(
        min_quality=0.0, get_center=False, check_fingerprint=False, compute_nfiq2=True,
        ppi=500.0,
    )
    return nbis.new_nbis_extractor(settings)


def png_bytes(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def moved(image: np.ndarray, *, shift_mm: tuple[float, float], angle_deg: float) -> np.ndarray:
    """The render shifted and rotated about its centre (white fill)."""
    h, w = image.shape
    m = cv2.getRotationMatrix2D((w / 2, h / 2), angle_deg, 1.0)
    m[:, 2] += np.array(shift_mm) * PX_PER_MM
    return cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=255)


def truth_keeps(pattern: FingerprintPattern, xy_mm: np.ndarray, *,
                border_mm: float = 1.0,
                singular_zone_mm: float = 1.5) -> np.ndarray:
    """(N,) bool: rolled-plane points (N, 2) where the generator keeps ground truth (more
    than ``border_mm`` inside its mask, ``singular_zone_mm`` from its singular points)."""
    inner = ndimage.distance_transform_edt(np.pad(pattern.mask, 1))[1:-1, 1:-1]
    rows = np.clip((xy_mm[:, 1] / pattern.pixel_mm).astype(int), 0, pattern.mask.shape[0] - 1)
    cols = np.clip((xy_mm[:, 0] / pattern.pixel_mm).astype(int), 0, pattern.mask.shape[1] - 1)
    keep = inner[rows, cols] * pattern.pixel_mm > border_mm
    for sp in pattern.singular_points:
        keep &= np.hypot(xy_mm[:, 0] - sp.x_mm, xy_mm[:, 1] - sp.y_mm) > singular_zone_mm
    return keep


def compare_minutiae(
    pattern: FingerprintPattern, detected, *, border_mm: float = 1.0,
    singular_zone_mm: float = 1.5,
) -> dict[str, float]:
    """Recall, precision and median angle error (deg) of NBIS minutiae vs the ground truth."""

    truth = np.array([(m.x_mm, m.y_mm, m.angle_rad) for m in pattern.minutiae]).reshape(-1, 3)
    det = np.array(
        [((d.x() + 0.5) / PX_PER_MM, (d.y() + 0.5) / PX_PER_MM, np.deg2rad(d.angle()))
         for d in detected]
    ).reshape(-1, 3)
    evaluated = truth_keeps(pattern, det[:, :2], border_mm=border_mm,
                            singular_zone_mm=singular_zone_mm)
    d = np.hypot(truth[:, None, 0] - det[None, :, 0], truth[:, None, 1] - det[None, :, 1])
    if d.size == 0:
        return {"recall": 0.0, "precision": 0.0, "angle_deg": float("nan")}
    recall = float((d.min(axis=1) <= MATCH_RADIUS_MM).mean())
    precision = float((d[:, evaluated].min(axis=0) <= MATCH_RADIUS_MM).mean())
    nearest = d.argmin(axis=1)
    hit = d.min(axis=1) <= MATCH_RADIUS_MM
    diff = np.angle(np.exp(1j * (det[nearest[hit], 2] - truth[hit, 2])))
    return {"recall": recall, "precision": precision,
            "angle_deg": float(np.median(np.degrees(np.abs(diff))))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=6, help="identities 0..N-1")
    args = parser.parse_args(argv)
    extractor = nbis_extractor()
    patterns, renders, times = [], [], []
    for seed in range(args.seeds):
        t0 = time.perf_counter()
        patterns.append(generate_fingerprint(seed))
        times.append(time.perf_counter() - t0)
        renders.append(render_rolled_print(patterns[-1]))
    templates = [extractor.extract_minutiae(png_bytes(r)) for r in renders]
    print(f"{'seed':>4} {'class':<11} {'gen s':>5} {'GT':>3} {'end/bif':>7} {'NBIS':>4} "
          f"{'recall':>6} {'prec':>5} {'dAng':>5} {'genuine':>7} {'impostor':>8} {'NFIQ2':>5}")
    rows = []
    for i, (pattern, render, template) in enumerate(zip(patterns, renders, templates, strict=True)):
        stats = compare_minutiae(pattern, template.get())
        other = moved(render, shift_mm=(0.6, -0.4), angle_deg=4.0)
        genuine = template.compare(extractor.extract_minutiae(png_bytes(other)))
        impostor = template.compare(templates[(i + 1) % len(templates)])
        nfiq2 = template.quality().score
        endings = sum(m.kind.value == "ending" for m in pattern.minutiae)
        rows.append((stats["recall"], stats["precision"], genuine, impostor, nfiq2))
        print(f"{pattern.seed:>4} {pattern.pattern_class.value:<11} {times[i]:>5.2f} "
              f"{len(pattern.minutiae):>3} {endings:>3}/{len(pattern.minutiae) - endings:<3} "
              f"{len(template.get()):>4} {stats['recall']:>6.2f} {stats['precision']:>5.2f} "
              f"{stats['angle_deg']:>5.1f} {genuine:>7} {impostor:>8} {nfiq2:>5}")
    r = np.array(rows, dtype=float)
    print(f"median recall {np.median(r[:, 0]):.2f}, precision {np.median(r[:, 1]):.2f}; "
          f"genuine min {r[:, 2].min():.0f} vs impostor max {r[:, 3].max():.0f}; "
          f"NFIQ2 median {np.median(r[:, 4]):.0f}; generation median {np.median(times):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
