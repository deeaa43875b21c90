"""bench/fingerprint_records.py: the FNMR at FMR 0.1 % and what a min_nfiq2 would reject,
on scores whose answers are known; the records read-back on a real print."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from rig_prints import true_rolled_print

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from bench_fingerprint import error_rates
from fingerprint_records import RecordsCheck, nfiq2_threshold_effect


def test_fnmr_at_fmr_takes_the_lowest_threshold_within_the_false_match_rate() -> None:
    impostor = np.concatenate([np.zeros(998), [30.0, 50.0]])
    genuine = np.array([20.0, 40.0, 45.0, 60.0])
    # FMR 0.1 %: one impostor of 1000 may match, so the threshold is 40: 20 misses.
    assert error_rates(genuine, impostor, fmr_max=0.001)[1] == pytest.approx(0.25)
    # FMR 0.2 %: both may, the threshold drops to 20 and every genuine score matches.
    assert error_rates(genuine, impostor, fmr_max=0.002)[1] == pytest.approx(0.0)


def test_a_threshold_rejects_low_prints_and_their_genuine_comparisons_fail() -> None:
    nfiq2 = {"0.0": 60.0, "0.1": 25.0, "1.0": 55.0, "1.1": float("nan")}
    genuine = [(80.0, "0.0 v 0.1"), (70.0, "0.0 v 0.T"), (75.0, "1.0 v 1.1"),
               (90.0, "1.1 v 1.T")]
    impostor = [(5.0, f"{a} v {b}") for a in ("0.0", "0.1") for b in ("1.0", "1.1")]
    impostor += [(5.0, "0.T v 1.0")] * 1000
    out = nfiq2_threshold_effect("m.", nfiq2, genuine, impostor, error_rates)
    assert out["m.nfiq2_0.rejected_pct"] == 0 and out["m.nfiq2_0.fnmr_at_fmr01_pct"] == 0
    # 30 rejects 0.1 (25) and 1.1 (no score): 3 of the 4 genuine comparisons fail.
    assert out["m.nfiq2_30.rejected_pct"] == pytest.approx(50.0)
    assert out["m.nfiq2_30.fnmr_at_fmr01_pct"] == pytest.approx(75.0)


def test_the_records_of_a_print_read_back() -> None:
    check = RecordsCheck()
    check.check(true_rolled_print(3), "3.0")
    check.check(np.full((80, 80), 200, np.uint8), "blank")  # NBIS finds nothing: not made
    figures = check.figures()
    assert figures["fingerprint.records.checked"] == 2
    assert figures["fingerprint.records.read_back"] == 1
    assert check.failures[0].startswith("blank: not made")
