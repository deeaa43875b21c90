"""The contact-print arm of bench/bench_fingerprint.py: 3D prints against plate impressions.

Interoperability with the contact prints in the galleries (issue 23, item 2). For each
synthetic identity, ``CONTACTS`` contact impressions as a 500 ppi plate scanner makes them:
``fingerps_driver.simulation.contact_impression`` (the central pad pressed flat: a Hertzian
contact ellipse whose size follows the drawn force; the plastic distortion of Cappelli,
Maio & Maltoni, ICAPR 2001: a close-contact region that does not move, an external region
dragged by a rigid transform of up to +-3 deg and 1 mm, a transition between them under
their brake function; the FTIR scanner's look: dark ridges, dryness, noise, a random
placement of +-15 deg and +-2 mm on the plate), each impression its own draw (seed
``[CONTACT_SEED, identity, k]``). The 3D prints are the benchmark's captures' prints (the
same templates), the ground-truth rolled prints ``rig.rolled_print()``.

Figures (bozorth3 through nbis-py; a refused 3D print scores 0 as in the benchmark):

- ``fingerprint.<model>.contact.genuine_3d_median`` (and ``_min``): every 3D capture of a
  finger vs every contact impression of it (IDENTITIES x CAPTURES x CONTACTS scores);
- ``fingerprint.contact.genuine_cc_median`` (and ``_min``): contact vs contact of one
  finger (IDENTITIES x C(CONTACTS, 2));
- ``fingerprint.<model>.contact.ratio`` = genuine_3d_median / genuine_cc_median, target
  >= ``TARGETS['ratio']`` (0.8); ``ratio_p05`` / ``ratio_p95``: its 90 % interval over
  the fingers resampled with replacement (``BOOTSTRAP_DRAWS``);
- impostors: ``fingerprint.<model>.contact.impostor_median`` / ``_max`` (every 3D capture
  vs every contact impression of every other finger), ``fingerprint.contact.impostor_cc_*``
  (contact vs contact of two fingers, each pair of fingers once). Target "impostors
  unchanged": the 3D-vs-contact impostor median and max not above the contact-vs-contact
  ones by more than ``TARGETS['impostor_rise']`` (25 %);
- ``eer_pct`` and ``fnmr_at_fmr01_pct`` (FNMR at FMR <= 0.1 %) of 3D-vs-contact (per
  model) and of contact-vs-contact; FMR 0.1 % needs >= 1000 impostor scores: the counts
  are the ``*_impostors`` / ``*_genuine`` figures (3420 and 1710 with 20 x 3 x 3);
- diagnosis: ``fingerprint.contact.genuine_truth_median``, the ground-truth rolled print
  vs each contact impression of its finger, and its ``truth_ratio`` over genuine_cc: what a
  perfect rolled print gets (the share of the rolled-vs-plain difference: area,
  distortion), against which the 3D print's own share is read; ``nfiq2_median`` and
  ``minutiae_median`` of the impressions.

Run with the benchmark (``bench_fingerprint.run()`` calls :func:`run_arm`), or alone on the
same captures: ``python bench/fingerprint_contact_arm.py [--identities N] [--cache DIR]``
(``--cache`` keeps the 3D prints as PNG files, so a second run skips the reconstructions;
``--variants`` adds the ratio under other distortions of the contact model, ``VARIANTS``;
``--diagnose`` adds the 3D prints enlarged by their known mean scale error,
``KNOWN_SCALE``, and scored again: the share of the print's scale in the ratio).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from check_fingerprint_pattern import png_bytes

from fingerps_driver.simulation.contact_impression import ContactScanner, contact_impression
from fingerps_driver.simulation.fingerprint_pattern import render_rolled_print
from fingerps_driver.simulation.fingerprint_relief import relief_for_identity

CONTACTS = 3
CONTACT_SEED = 23
FMR_TARGET = 0.001
TARGETS = {"ratio": 0.8, "impostor_rise": 0.25}
#: ``--diagnose``: the 3D prints' known mean scale s (print mm -> rolled mm; the
#: benchmark's ``fingerprint.<model>.scale_pct_mean``, README: +0.41 % HK, +2.69 %
#: Lambertian since issue 23's scale fix; +2.65 % and +4.38 % before): the print images
#: enlarged by s, scored again.
KNOWN_SCALE = {"hk": 1.0041, "lambert": 1.0269}
#: ``--variants``: the model with other distortions (diagnosis of the ratio's dependence
#: on it, not the benchmark's model): no drag; a sharper brake (k 1.25 mm, region a 0.3).
VARIANTS = {"no_drag": {"drag_translation_mm": 0.0, "drag_rotation_deg": 0.0},
            "sharp_brake": {"brake_k_mm": 1.25, "close_fraction": 0.3}}
BOOTSTRAP_DRAWS = 2000

ErrorRates = Callable[..., tuple[float, float]]


def contact_templates(extractor, identities: int, *, seed: int = CONTACT_SEED,
                      contacts: int = CONTACTS, scanner: ContactScanner | None = None
                      ) -> tuple[list[list], list[float], list[int]]:
    """The contact impressions' templates [identity][k], their NFIQ 2 and minutiae counts
    (``scanner``: the model's defaults when None)."""
    templates, nfiq2, counts = [], [], []
    for identity in range(identities):
        relief = relief_for_identity(identity)
        row = []
        for k in range(contacts):
            impression = contact_impression(relief, seed=[seed, identity, k],
                                            scanner=scanner)
            template = extractor.extract_minutiae(png_bytes(impression.image))
            nfiq2.append(float(template.quality().score))
            counts.append(len(template.get()))
            row.append(template)
        templates.append(row)
    return templates, nfiq2, counts


def _score(a, b) -> float:
    return 0.0 if a is None or b is None else float(a.compare(b))


def score_sets(prints: Sequence[Sequence], contacts: Sequence[Sequence]
               ) -> tuple[np.ndarray, np.ndarray]:
    """(genuine, impostor) scores of prints [identity][capture] (None: refused, 0) against
    contact templates [identity][k]: every print vs every contact of its finger, and vs
    every contact of every other finger."""
    genuine, impostor = [], []
    for i, captures in enumerate(prints):
        for p in captures:
            for j, row in enumerate(contacts):
                scores = [_score(p, c) for c in row]
                (genuine if j == i else impostor).extend(scores)
    return np.array(genuine), np.array(impostor)


def contact_vs_contact(contacts: Sequence[Sequence]) -> tuple[np.ndarray, np.ndarray]:
    """(genuine, impostor): pairs of one finger's impressions; every impression of finger i
    vs every impression of finger j > i."""
    genuine, impostor = [], []
    for i, row in enumerate(contacts):
        genuine += [_score(row[a], row[b]) for a in range(len(row))
                    for b in range(a + 1, len(row))]
        for other in contacts[i + 1:]:
            impostor += [_score(a, b) for a in row for b in other]
    return np.array(genuine), np.array(impostor)


def ratio_interval(genuine_3d: np.ndarray, genuine_cc: np.ndarray, identities: int, *,
                   draws: int = BOOTSTRAP_DRAWS, seed: int = 0) -> tuple[float, float]:
    """5th and 95th percentiles of the ratio of medians over fingers resampled with
    replacement (the scores are grouped by finger, in finger order)."""
    a = genuine_3d.reshape(identities, -1)
    b = genuine_cc.reshape(identities, -1)
    picks = np.random.default_rng(seed).integers(0, identities, (draws, identities))
    ratios = [np.median(a[i]) / np.median(b[i]) for i in picks]
    return float(np.percentile(ratios, 5)), float(np.percentile(ratios, 95))


def _rates(prefix: str, genuine: np.ndarray, impostor: np.ndarray,
           error_rates: ErrorRates) -> dict[str, float]:
    eer, fnmr = error_rates(genuine, impostor, fmr_max=FMR_TARGET)
    return {
        prefix + "genuine": float(len(genuine)),
        prefix + "impostors": float(len(impostor)),
        prefix + "eer_pct": 100 * eer,
        prefix + "fnmr_at_fmr01_pct": 100 * fnmr,
        prefix + "impostor_median": float(np.median(impostor)),
        prefix + "impostor_max": float(np.max(impostor)),
    }


def run_arm(extractor, prints: dict[str, Sequence[Sequence]], truth_templates: Sequence,
            error_rates: ErrorRates, *, contacts: tuple | None = None) -> dict[str, float]:
    """The arm's figures (module docstring).

    Parameters
    ----------
    extractor
        nbis-py's extractor (``check_fingerprint_pattern.nbis_extractor``).
    prints : {model name: [identity][capture] template or None}
        The 3D prints' templates (None: refused).
    truth_templates : [identity] template
        The ground-truth rolled prints' templates.
    error_rates : callable
        ``bench_fingerprint.error_rates(genuine, impostor, fmr_max=...)`` -> (EER, FNMR).
    contacts : tuple, optional
        ``contact_templates(extractor, identities)`` made already (default: made here).
    """
    identities = len(truth_templates)
    contacts, nfiq2, counts = (contact_templates(extractor, identities) if contacts is None
                               else contacts)
    g_cc, i_cc = contact_vs_contact(contacts)
    g_truth, _ = score_sets([[t] for t in truth_templates], contacts)
    cc_median = float(np.median(g_cc))
    f: dict[str, float] = {
        "fingerprint.contact.impressions": float(identities * CONTACTS),
        "fingerprint.contact.nfiq2_median": float(np.median(nfiq2)),
        "fingerprint.contact.minutiae_median": float(np.median(counts)),
        "fingerprint.contact.genuine_cc_median": cc_median,
        "fingerprint.contact.genuine_cc_min": float(np.min(g_cc)),
        "fingerprint.contact.genuine_truth_median": float(np.median(g_truth)),
        "fingerprint.contact.truth_ratio": float(np.median(g_truth)) / cc_median,
    }
    f.update(_rates("fingerprint.contact.cc_", g_cc, i_cc, error_rates))
    for model, per_id in prints.items():
        g, imp = score_sets(per_id, contacts)
        p = f"fingerprint.{model}.contact."
        f[p + "genuine_3d_median"] = float(np.median(g))
        f[p + "genuine_3d_min"] = float(np.min(g))
        f[p + "ratio"] = float(np.median(g)) / cc_median
        f[p + "ratio_p05"], f[p + "ratio_p95"] = ratio_interval(g, g_cc, identities)
        f.update(_rates(p, g, imp, error_rates))
    return f


def contact_table(f: dict[str, float], models: Sequence[str]) -> None:
    """The arm's table and the verdict on its targets, after the benchmark's table."""
    c = "fingerprint.contact."
    print(f"\ncontact arm: {f[c + 'impressions']:.0f} impressions ({CONTACTS} a finger; "
          f"NFIQ 2 median {f[c + 'nfiq2_median']:.0f}, {f[c + 'minutiae_median']:.0f} "
          "minutiae median)")
    print(f"{'':<44}{'genuine med/min':>16}{'impostor med/max':>18}{'EER %':>8}"
          f"{'FNMR@0.1%':>10}{'scores g/i':>12}")
    rows = [("contact vs contact", c + "genuine_cc_", c + "cc_")] + [
        (f"{m} 3D vs contact", f"fingerprint.{m}.contact.genuine_3d_",
         f"fingerprint.{m}.contact.") for m in models]
    for label, g, r in rows:
        print(f"{label:<44}{f[g + 'median']:>9.0f} / {f[g + 'min']:<4.0f}"
              f"{f[r + 'impostor_median']:>10.0f} / {f[r + 'impostor_max']:<5.0f}"
              f"{f[r + 'eer_pct']:>8.2f}{f[r + 'fnmr_at_fmr01_pct']:>10.2f}"
              f"{f[r + 'genuine']:>6.0f}/{f[r + 'impostors']:<5.0f}")
    print(f"{'ground-truth rolled print vs contact':<44}"
          f"{f[c + 'genuine_truth_median']:>9.0f}      (ratio to contact-contact "
          f"{f[c + 'truth_ratio']:.2f})")
    for m in models:
        p = f"fingerprint.{m}.contact."
        print(f"{m}: 3D-vs-contact genuine median / contact-vs-contact = {f[p + 'ratio']:.2f} "
              f"(90 % over fingers resampled: {f[p + 'ratio_p05']:.2f}-"
              f"{f[p + 'ratio_p95']:.2f}; target >= {TARGETS['ratio']})")
    for m in models:
        p = f"fingerprint.{m}.contact."
        misses = []
        if f[p + "ratio"] < TARGETS["ratio"]:
            scale = f.get(f"fingerprint.{m}.scale_pct_mean")
            scale = "" if scale is None else f"{scale:+.1f} % mean; "
            cause = (
                "the ground-truth rolled print itself gets "
                f"{f[c + 'truth_ratio']:.2f} of contact-vs-contact, so "
                + ("most of the gap is rolled-vs-plain (a larger print's other minutiae, "
                   "the contact's distortion), not the 3D print"
                   if f[c + "truth_ratio"] < TARGETS["ratio"] else
                   f"it is the 3D print's own share: its scale ({scale}'python "
                   "bench/fingerprint_contact_arm.py --diagnose' scores the prints "
                   "enlarged by it), its minutiae (recall / precision of the benchmark's "
                   "table), the unrolling's residual distortion"))
            misses.append(f"ratio {f[p + 'ratio']:.2f} < {TARGETS['ratio']} (short by "
                          f"{TARGETS['ratio'] - f[p + 'ratio']:.2f}): {cause}")
        rise = 1.0 + TARGETS["impostor_rise"]
        for key in ("impostor_median", "impostor_max"):
            if f[p + key] > rise * max(f[c + "cc_" + key], 1.0):
                misses.append(f"3D-vs-contact {key} {f[p + key]:.0f} > "
                              f"{rise:.2f} x contact-vs-contact {f[c + 'cc_' + key]:.0f} "
                              "(the 3D print's spurious minutiae pair with strangers')")
        print(f"{m} contact arm: " + ("every target met" if not misses else
                                      "MISSED: " + "; ".join(misses)))


def _captured_prints(identities: int, cache: Path | None) -> tuple[dict, list]:
    """The benchmark's captures (same poses and seeds) reconstructed and printed: the print
    images {model: [identity][capture] uint8 or None} and the ground-truth prints."""
    import cv2
    from bench_fingerprint import (
        CAPTURES,
        MODELS,
        SEED,
        calibrations,
        draw_pose,
        posed_rig,
        reconstructed_print,
    )

    from fingerps_driver.simulation import Scene
    from fingerps_recon.errors import RolledPrintError

    prepared = None
    images = {m.value: [] for m in MODELS}
    truths = []
    for identity in range(identities):
        for m in MODELS:
            images[m.value].append([])
        for capture in range(CAPTURES):
            rig = None
            for m in MODELS:
                path = None if cache is None else cache / f"{m.value}_{identity}_{capture}.png"
                refused = None if path is None else path.with_suffix(".refused")
                if path is not None and path.exists():
                    images[m.value][identity].append(cv2.imread(str(path), 0))
                    continue
                if refused is not None and refused.exists():
                    images[m.value][identity].append(None)
                    continue
                if rig is None:
                    prepared = prepared or calibrations()
                    rig = posed_rig(identity, draw_pose(identity, capture))
                    burst = rig.render_burst(Scene.FINGER, seed=[SEED, identity, capture])
                try:
                    _, fp = reconstructed_print(rig, burst, prepared[m], m)
                except RolledPrintError:
                    images[m.value][identity].append(None)
                    if refused is not None:
                        refused.touch()
                    continue
                images[m.value][identity].append(fp.image)
                if path is not None:
                    cv2.imwrite(str(path), fp.image)
            print(f"finger {identity} capture {capture}", flush=True)
        truths.append(render_rolled_print(relief_for_identity(identity).pattern))
    return images, truths


def main(argv: list[str] | None = None) -> int:
    import cv2
    from bench_fingerprint import IDENTITIES, error_rates
    from check_fingerprint_pattern import nbis_extractor

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--identities", type=int, default=IDENTITIES)
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder keeping the 3D prints (PNG) between runs")
    parser.add_argument("--diagnose", action="store_true",
                        help="also score the 3D prints scaled up by the mean scale error")
    parser.add_argument("--variants", action="store_true",
                        help="also the contact model's other distortions (VARIANTS)")
    args = parser.parse_args(argv)
    if args.cache is not None:
        args.cache.mkdir(parents=True, exist_ok=True)
    extractor = nbis_extractor()
    images, truths = _captured_prints(args.identities, args.cache)

    def templates(factor: float = 1.0) -> dict:
        out = {}
        for model, per_id in images.items():
            out[model] = [[None if im is None else extractor.extract_minutiae(png_bytes(
                im if factor == 1.0 else cv2.resize(im, None, fx=factor, fy=factor,
                                                   interpolation=cv2.INTER_CUBIC)))
                           for im in caps] for caps in per_id]
        return out

    truth_templates = [extractor.extract_minutiae(png_bytes(t)) for t in truths]
    contacts = contact_templates(extractor, len(truth_templates))
    figures = run_arm(extractor, templates(), truth_templates, error_rates, contacts=contacts)
    if args.diagnose:
        for model in images:
            factor = KNOWN_SCALE[model]
            scaled = run_arm(extractor, {model: templates(factor)[model]}, truth_templates,
                             error_rates, contacts=contacts)
            p = f"fingerprint.{model}.contact."
            figures[p + "ratio_scaled"] = scaled[p + "ratio"]
            figures[p + "genuine_3d_median_scaled"] = scaled[p + "genuine_3d_median"]
    if args.variants:
        for name, changes in VARIANTS.items():
            made = contact_templates(extractor, len(truth_templates),
                                     scanner=ContactScanner(**changes))
            varied = run_arm(extractor, templates(), truth_templates, error_rates,
                             contacts=made)
            for key in ("fingerprint.contact.genuine_cc_median",
                        "fingerprint.contact.truth_ratio",
                        *(f"fingerprint.{m}.contact.{k}" for m in images
                          for k in ("genuine_3d_median", "ratio"))):
                figures[f"{key}_{name}"] = varied[key]
    contact_table(figures, list(images))
    for name, value in figures.items():
        print(f"  {name:<56}{value:12.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
