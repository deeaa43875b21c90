"""The demo's timing figures (fingerps_driver.demo_figures) and its summary lines
(demo.print_summary): the first burst apart from the steady state after it, null where there
is nothing to measure, one JSON line a script can read."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from fingerps_driver import demo
from fingerps_driver.demo_figures import ms, timing_figures

STAMP0 = 1_700_000_000_000_000_000


def _bursts(count: int, *, period_s: float = 0.2, first_ms: float = 900.0,
            steady_ms: float = 80.0, lost: tuple[int, ...] = ()):
    """Request times, stamps and the clouds of ``count`` bursts at ``period_s``: the first
    takes ``first_ms``, the others ``steady_ms + i`` ms; the bursts in ``lost`` never come."""
    requested = [10.0 + i * period_s for i in range(count)]
    stamps = [STAMP0 + int(i * period_s * 1e9) for i in range(count)]
    latency, arrival = {}, {}
    for i, (t, stamp) in enumerate(zip(requested, stamps, strict=True)):
        if i in lost:
            continue
        latency[stamp] = first_ms if i == 0 else steady_ms + i
        arrival[stamp] = t + latency[stamp] / 1e3
    return requested, stamps, latency, arrival


def test_the_first_burst_is_apart_from_the_steady_state():
    requested, stamps, latency, arrival = _bursts(20)
    f = timing_figures(requested, stamps, latency, arrival)
    assert f["e2e.first_latency_ms"] == 900.0
    assert f["steady_bursts_captured"] == 19 == len(stamps) - 1
    assert f["steady_bursts_reconstructed"] == 19
    steady = [80.0 + i for i in range(1, 20)]
    assert f["e2e.latency_ms_median"] == pytest.approx(np.median(steady))  # 90, not the 900
    assert f["e2e.latency_ms_p95"] == pytest.approx(np.percentile(steady, 95))
    # 19 clouds from the second request (10.2 s) to the last cloud (13.8 s + 99 ms)
    assert f["e2e.bursts_per_s"] == pytest.approx(19 / (3.6 + 0.099))


def test_lost_bursts_count_against_the_steady_state_and_a_lost_first_is_null():
    requested, stamps, latency, arrival = _bursts(10, lost=(0, 4, 9))
    latency[STAMP0 - 1] = 5.0  # a cloud of no captured burst is ignored
    arrival[STAMP0 - 1] = 0.0
    f = timing_figures(requested, stamps, latency, arrival)
    assert f["e2e.first_latency_ms"] is None
    assert (f["steady_bursts_captured"], f["steady_bursts_reconstructed"]) == (9, 7)
    assert f["e2e.latency_ms_median"] == pytest.approx(np.median([81, 82, 83, 85, 86, 87, 88]))
    assert f["e2e.bursts_per_s"] == pytest.approx(7 / (1.6 - 0.2 + 0.088))


def test_one_burst_has_no_steady_state():
    requested, stamps, latency, arrival = _bursts(1)
    f = timing_figures(requested, stamps, latency, arrival)
    assert f["e2e.first_latency_ms"] == 900.0
    assert f["steady_bursts_captured"] == f["steady_bursts_reconstructed"] == 0
    assert f["e2e.latency_ms_median"] is f["e2e.latency_ms_p95"] is f["e2e.bursts_per_s"] is None
    assert json.loads(json.dumps(f, allow_nan=False))["e2e.bursts_per_s"] is None


def test_mismatched_or_empty_inputs_are_refused():
    with pytest.raises(ValueError, match="no burst"):
        timing_figures([], [], {}, {})
    with pytest.raises(ValueError, match="2 request times for 1 stamps"):
        timing_figures([0.0, 0.2], [STAMP0], {}, {})


def test_ms_says_n_a_for_null():
    assert (ms(None), ms(931.4), ms(12.25, 1)) == ("n/a", "931 ms", "12.2 ms")


def _figures(**timing) -> dict:
    requested, stamps, latency, arrival = _bursts(20)
    return {
        "bursts_requested": 20, "bursts_captured": 20, "bursts_reconstructed": 20,
        "recon_bursts_dropped": 0,
        **timing_figures(requested, stamps, latency, arrival),
        "e2e.mae_deg": 1.29, "capture_ms_median": 41.0, "normals_median_deg": 1.21,
        "normals_p95_deg": 2.48, "finger_coverage": 1.0, "light_direction_error_deg_max": 0.1,
        "led_position_error_mm_max": 2.4, "sphere_placements": 3, "model": "hk",
        "calibrate_flat_field_s": 5.1, "calibrate_lights_s": 1.1, "total_s": 14.0, **timing,
    }


def test_the_summary_has_the_warm_up_and_the_steady_state_on_lines_of_their_own():
    stream = io.StringIO()
    demo.print_summary(_figures(), Path("out/demo"), [0, 0, 0, 0], stream=stream)
    lines = stream.getvalue().splitlines()
    assert "  bursts captured / reconstructed : 20 / 20 (0 dropped by recon_node)" in lines
    assert "  first burst (warm-up) latency   : 900 ms" in lines
    assert ("  steady state, bursts 2-20       : 19 of 19 reconstructed, throughput 5.14 "
            "bursts/s") in lines
    assert "  steady burst -> cloud latency   : median 90 ms, p95 98 ms" in lines
    assert "  normals vs ground truth (finger): mean 1.29 deg" in "\n".join(lines)
    # every label ends in the same column
    assert {line.index(":") for line in lines[1:]} == {34}


def test_the_summary_of_a_single_burst_says_n_a():
    requested, stamps, latency, arrival = _bursts(1)
    figures = _figures(**timing_figures(requested, stamps, latency, arrival),
                       recon_bursts_dropped=None, bursts_captured=1)
    stream = io.StringIO()
    demo.print_summary(figures, Path("out"), [0, 0, 0, 0], stream=stream)
    text = stream.getvalue()
    assert "  bursts captured / reconstructed : 1 / 20\n" in text
    assert "  steady state                    : 0 of 0 reconstructed, throughput n/a" in text
    assert "median n/a, p95 n/a" in text


def test_the_json_figures_are_strict_json():
    figures = {"led_position_error_mm_max": float("nan"), "e2e.bursts_per_s": float("inf"),
               "e2e.mae_deg": 1.29, "model": "hk", "bursts_captured": 20,
               "e2e.first_latency_ms": None}
    line = json.dumps(demo.json_figures(figures), allow_nan=False)
    assert json.loads(line) == {"led_position_error_mm_max": None, "e2e.bursts_per_s": None,
                                "e2e.mae_deg": 1.29, "model": "hk", "bursts_captured": 20,
                                "e2e.first_latency_ms": None}
