"""The fingerprint benchmark's records and quality-threshold figures (bench_fingerprint.py).

- :class:`RecordsCheck`: each print's records (``records.print_records``: WSQ, ISO/IEC
  19794-2, ANSI/NIST-ITL) made and read back by readers independent of the writers: the WSQ
  image by NBIS's decoder (within ``MAX_RMS_ERROR`` of the print), the ISO record and the
  transaction by ``tests/record_readers.py`` (written from the standards' layouts): the
  record's size and minutiae agree with the print's, the transaction holds Type-1, Type-14
  with the same WSQ file and Type-9 with the same minutiae. ``fingerprint.records.*``:
  prints checked, read back, time to make them (median ms).
- :func:`nfiq2_threshold_effect`: what a Scan ``min_nfiq2`` would do to the benchmark's
  captures: the share of prints it rejects (the user is asked to try again) and the FNMR at
  FMR 0.1 % when a rejected capture's genuine comparisons count as non-matches (failure to
  acquire included) and it takes part in no impostor comparison.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from record_readers import read_ansi_nist, read_iso_19794_2_2005

from fingerps_recon.records.print_records import make_print_records
from fingerps_recon.records.wsq_image import MAX_RMS_ERROR, decode_wsq

#: ``min_nfiq2`` values whose effect is reported (0: not judged, the Scan default).
NFIQ2_THRESHOLDS = (0, 20, 30, 40, 50)
#: False match rate of the operating point, fraction.
FMR_OPERATING = 0.001

ErrorRates = Callable[..., tuple[float, float]]


@dataclass
class RecordsCheck:
    """Prints whose records were made and read back, with what failed and the times."""

    checked: int = 0
    read_back: int = 0
    times_ms: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def check(self, image: np.ndarray, label: str) -> None:
        """Make the records of one print and read each one back (module docstring)."""
        self.checked += 1
        t0 = time.perf_counter()
        made = make_print_records(image, transaction_control=f"bench-{label}")
        self.times_ms.append(1e3 * (time.perf_counter() - t0))
        problem = _read_back_problem(image, made)
        if problem:
            self.failures.append(f"{label}: {problem}")
        else:
            self.read_back += 1

    def figures(self) -> dict[str, float]:
        return {"fingerprint.records.checked": float(self.checked),
                "fingerprint.records.read_back": float(self.read_back),
                "fingerprint.records.ms_median": float(np.median(self.times_ms))
                if self.times_ms else float("nan")}


def _read_back_problem(image: np.ndarray, made) -> str:
    """Why the records of ``image`` do not read back, or ''."""
    if made.wsq is None or made.iso_template is None or made.transaction is None:
        return "not made: " + "; ".join(f"{k}: {v}" for k, v in made.reasons.items())
    decoded, ppi = decode_wsq(made.wsq)
    rms = float(np.sqrt(np.mean((decoded.astype(np.float64) - image) ** 2)))
    if ppi != 500 or decoded.shape != image.shape or rms > MAX_RMS_ERROR:
        return f"WSQ {decoded.shape} at {ppi} ppi, RMS {rms:.1f}"
    iso = read_iso_19794_2_2005(made.iso_template)
    found = [(m["x"], m["y"]) for m in iso["minutiae"]]
    if (iso["width"], iso["height"]) != (image.shape[1], image.shape[0]) or found != list(
            zip(made.minutiae.x_px.tolist(), made.minutiae.y_px.tolist(), strict=True)):
        return "ISO record's size or minutiae differ from the print's"
    records = read_ansi_nist(made.transaction)
    if [t for t, _ in records] != [1, 14, 9] or records[1][1][999] != made.wsq:
        return "transaction's records or WSQ image differ"
    if [(int(row[1]), int(row[2])) for row in records[2][1][137]] != found:
        return "transaction's Type-9 minutiae differ from the ISO record's"
    return ""


def nfiq2_threshold_effect(prefix: str, nfiq2: dict[str, float],
                           genuine: list[tuple[float, str]],
                           impostor: list[tuple[float, str]],
                           error_rates: ErrorRates) -> dict[str, float]:
    """``<prefix>nfiq2_<t>.rejected_pct`` and ``.fnmr_at_fmr01_pct`` for each threshold t of
    :data:`NFIQ2_THRESHOLDS` (module docstring); ``error_rates`` is the benchmark's
    (``bench_fingerprint.error_rates``: EER and FNMR at FMR <= ``fmr_max``).

    ``nfiq2`` maps a capture's label ("i.c") to its print's NFIQ 2 (NaN: no score, rejected
    by any threshold above 0); comparisons are (score, "a v b") with captures and
    ground-truth prints ("i.T", never rejected) on either side.
    """
    out: dict[str, float] = {}
    for t in NFIQ2_THRESHOLDS:
        rejected = {c for c, q in nfiq2.items() if t > 0 and not q >= t}

        def hit(label: str, rejected: set[str] = rejected) -> bool:
            return any(side in rejected for side in label.split(" v "))

        gen = np.array([-1.0 if hit(label) else score for score, label in genuine])
        imp = np.array([score for score, label in impostor if not hit(label)])
        key = f"{prefix}nfiq2_{t}."
        out[key + "rejected_pct"] = 100.0 * len(rejected) / max(len(nfiq2), 1)
        out[key + "fnmr_at_fmr01_pct"] = 100.0 * error_rates(gen, imp,
                                                             fmr_max=FMR_OPERATING)[1]
    return out


def records_table(f: dict[str, float], models: list[str], failures: list[str]) -> None:
    """Print the records' read-back and the NFIQ 2 thresholds' effect; name what missed."""
    checked, back = f["fingerprint.records.checked"], f["fingerprint.records.read_back"]
    print(f"\nrecords (HK prints): {back:.0f} of {checked:.0f} made and read back by "
          f"independent readers, {f['fingerprint.records.ms_median']:.0f} ms a print (median)")
    for failure in failures:
        print(f"  MISSED: {failure}")
    print(f"{'Scan min_nfiq2':<16}" + "".join(f"{m + ' rejected / FNMR@0.1%':>30}"
                                             for m in models))
    for t in NFIQ2_THRESHOLDS:
        cells = [f"{f[f'fingerprint.{m}.nfiq2_{t}.rejected_pct']:.1f} % / "
                 f"{f[f'fingerprint.{m}.nfiq2_{t}.fnmr_at_fmr01_pct']:.2f} %" for m in models]
        print(f"{t:<16}" + "".join(f"{c:>30}" for c in cells))
