"""bench/bench_e2e.py's harness logic without a graph: the ``--only`` scenarios, the keys a
window reports under its prefix, and which rates the sweep tries after the 5/s and 10/s
windows (the real-time targets' scenarios)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))

import bench_e2e  # noqa: E402
import run_all  # noqa: E402
from bench_e2e import Window  # noqa: E402


def window(rate: float, published: int, lost: int, seconds: float = 60.0) -> Window:
    return Window(rate, seconds, published, published - lost, lost,
                  (100.0,) * (published - lost), {})


@pytest.fixture
def tried(monkeypatch) -> list[float]:
    """The sweep's windows (20 s, so every rate is a whole number of bursts): every rate is
    delivered in full; lossless up to 12.5/s."""
    rates: list[float] = []

    def at_rate(observer, graph, rate, seconds):
        rates.append(rate)
        return window(rate, round(rate * 20), 0 if rate <= 12.5 else 3, 20.0)

    monkeypatch.setattr(bench_e2e, "at_rate", at_rate)
    return rates


def test_only_takes_known_scenarios_and_the_default_is_all():
    assert bench_e2e.parse_only("kiosk10,print") == ("kiosk10", "print")
    assert bench_e2e.parse_only(" kiosk10 , print ,") == ("kiosk10", "print")
    with pytest.raises(argparse.ArgumentTypeError, match="unknown scenario"):
        bench_e2e.parse_only("kiosk10,fast")
    with pytest.raises(argparse.ArgumentTypeError):
        bench_e2e.parse_only(",")
    assert set(bench_e2e.GRAPH_SCENARIOS) == set(bench_e2e.SCENARIOS) - {"demo"}


def test_a_window_reports_the_five_figures_under_its_prefix():
    figures = bench_e2e.window_figures("e2e.hk10", window(10.0, 600, 2))
    assert figures == {"e2e.hk10.bursts_per_s": 598 / 60, "e2e.hk10.published_per_s": 10.0,
                       "e2e.hk10.lost": 2.0, "e2e.hk10.latency_ms_median": 100.0,
                       "e2e.hk10.latency_ms_p95": 100.0}
    empty = bench_e2e.window_figures("e2e.hk", window(5.0, 300, 300))
    assert empty["e2e.hk.lost"] == 300.0 and math.isnan(empty["e2e.hk.latency_ms_median"])


def test_the_sweep_goes_up_from_a_lossless_10_per_s_until_a_window_loses(tried):
    best = bench_e2e.sweep(None, None, window(5.0, 300, 0), window(10.0, 600, 0), [])
    assert tried == [12.5, 15.0] and best == 12.5


def test_the_sweep_tries_between_after_a_lossy_10_per_s(tried):
    best = bench_e2e.sweep(None, None, window(5.0, 300, 0), window(10.0, 600, 40), [])
    assert tried == list(bench_e2e.SWEEP_BETWEEN) and best == 7.5


def test_the_sweep_goes_down_after_a_lossy_5_per_s_to_the_first_lossless(tried):
    best = bench_e2e.sweep(None, None, window(5.0, 300, 6), window(10.0, 600, 40), [])
    assert tried == [2.5] and best == 2.5


def test_a_driver_that_cannot_deliver_the_rate_ends_the_sweep(tried):
    best = bench_e2e.sweep(None, None, window(5.0, 300, 0), window(10.0, 420, 0), [])
    assert tried == [] and best == 7.0


def test_the_new_figures_are_kept_by_the_avx2_pass():
    is_speed = run_all.SPEED["bench_e2e"][1]
    for name in ("e2e.hk10.lost", "e2e.hk10.latency_ms_p95", "e2e.hk_print_rec.lost",
                 "e2e.hk_print_rec.prints", "e2e.hk_print_rec.recorder_not_written",
                 "e2e.hk.max_bursts_per_s"):
        assert is_speed(name)
