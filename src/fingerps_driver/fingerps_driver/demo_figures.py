"""The demo's timing figures: the first burst apart, the steady state over the bursts after it.

The first burst after a calibration meets the warm-up (recon_node prepares the calibration
for the camera, memory is cold), so its latency is reported on its own; latency (median,
p95) and throughput are over the bursts after it. Plain Python and numpy, no ROS: the demo
collects the times, this module turns them into figures (``tests/core/test_demo_figures.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

Figure = float | int | None
"""A figure of the demo's JSON: None (JSON null) when there is nothing to measure it on."""


def timing_figures(requested_s: Sequence[float], stamps_ns: Sequence[int],
                   latency_ms: Mapping[int, float],
                   arrival_s: Mapping[int, float]) -> dict[str, Figure]:
    """The first burst's latency and the steady state's figures.

    Parameters
    ----------
    requested_s : sequence of float
        ``time.monotonic()`` when burst i was requested, in request order.
    stamps_ns : sequence of int
        The header stamp (ns) of burst i as the driver captured it (same order).
    latency_ms, arrival_s : mapping of int to float
        By burst stamp, for every point cloud received: stamp -> cloud received (ms), and
        ``time.monotonic()`` of its receipt. Stamps of no captured burst are ignored.

    Returns
    -------
    dict
        ``e2e.first_latency_ms`` (None if the first burst's cloud never came),
        ``steady_bursts_captured`` (every burst after the first),
        ``steady_bursts_reconstructed`` (those whose cloud came),
        ``e2e.latency_ms_median`` / ``e2e.latency_ms_p95`` over them, and
        ``e2e.bursts_per_s``: their clouds / seconds from the second burst's request to the
        last of their clouds (None without a steady cloud).
    """
    if len(requested_s) != len(stamps_ns):
        raise ValueError(f"{len(requested_s)} request times for {len(stamps_ns)} stamps")
    if not stamps_ns:
        raise ValueError("no burst was captured")
    steady = [s for s in stamps_ns[1:] if s in latency_ms]
    latencies = np.array([latency_ms[s] for s in steady], dtype=np.float64)
    figures: dict[str, Figure] = {
        "e2e.first_latency_ms": (float(latency_ms[stamps_ns[0]])
                                 if stamps_ns[0] in latency_ms else None),
        "steady_bursts_captured": len(stamps_ns) - 1,
        "steady_bursts_reconstructed": len(steady),
        "e2e.latency_ms_median": None,
        "e2e.latency_ms_p95": None,
        "e2e.bursts_per_s": None,
    }
    if steady:
        span_s = max(arrival_s[s] for s in steady) - requested_s[1]
        figures["e2e.latency_ms_median"] = float(np.median(latencies))
        figures["e2e.latency_ms_p95"] = float(np.percentile(latencies, 95))
        figures["e2e.bursts_per_s"] = len(steady) / max(span_s, 1e-9)
    return figures


def ms(value: Figure, digits: int = 0) -> str:
    """A figure in ms for the summary: ``'123 ms'``, or ``'n/a'`` for None."""
    return "n/a" if value is None else f"{value:.{digits}f} ms"
