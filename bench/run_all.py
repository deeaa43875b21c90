"""Run every fingerps benchmark, print their tables, write bench/results.json.

Two passes. The native pass runs every benchmark in this process, as the machine is (or as
this process's switches say, when it was started with AVX-512 off: ``machine.native_avx512``
then reads 0; the AVX2 pass's switches are the machine's whole list all the same). The
AVX2 pass runs the speed benchmarks again in a process of their own started with AVX-512
turned off for numba, numpy and OpenCV (``simd_env.avx2_env``; each library reads its
switch at import, and the graph's node processes inherit the environment): what an AVX2
machine (most kiosk and robot PCs) would measure, on any x86-64 machine. Before it times
anything, that process compiles the reconstruction kernels for its target into numba's
on-disk cache (``kernel_warm_up``; minutes the first time, beside the native versions, which
stay), and every benchmark warms up before its timed runs.

The speed benchmarks and what the AVX2 pass keeps of them (:data:`SPEED`): ``driver.*``,
``driver.publish_ms.*``, ``recon.ms.*`` and ``recon.hk_kernel.*`` (not the ``recon.um.*``
accuracy figures), ``recon.publish_ms.*``/``recon.intake_ms.*``, ``e2e.*`` without the
demo's runs (the kiosk graph at 5 and at 10 bursts/s, the rate sweep, the first cloud, the
kiosk at 5 bursts/s with the print and the recorder: ``e2e.hk.*``, ``e2e.hk10.*``,
``e2e.first_cloud_s``, ``e2e.hk_print_rec.*``) and
``fingerprint.<model>.print_ms_median`` (the same captures printed, without NBIS). The
accuracy benchmarks (``recon.lambert.*`` accuracy, ``recon.hk_iter.*``, ``calib.*``, the
fingerprints' NBIS figures) run once, natively.

results.json is one flat JSON object: name -> number for the native figures (as before),
``<name>.avx2`` beside each speed figure for the AVX2 pass, and ``machine.*`` (see
``simd_env.machine_figures``): ``machine.cpu_model``, ``machine.simd_flags`` and the AVX2
pass's switches are strings, ``machine.native_avx512`` (1 / 0) and ``machine.cores`` numbers;
a reader that wants numbers skips the strings. The ``soak.*`` figures of ``make soak`` are
kept.

Usage (after ``make build``, with tools/ros_env.sh sourced): ``python bench/run_all.py``
(``--no-avx2`` skips the AVX2 pass and drops the ``.avx2`` figures of an earlier run).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_calib
import bench_chunk_compression
import bench_driver
import bench_driver_publish
import bench_e2e
import bench_fingerprint
import bench_firmware
import bench_hk_iterations
import bench_many_lights
import bench_recon_accuracy
import bench_recon_publish
import bench_recon_speed
import simd_env
from figures_report import print_figures

SEPARATE_PREFIXES = ("soak.",)
"""Figures of benchmarks not in ``make bench`` (``make soak``), kept when it rewrites the file."""

BENCHMARKS = (bench_driver, bench_driver_publish, bench_recon_speed, bench_recon_publish,
              bench_recon_accuracy, bench_hk_iterations, bench_many_lights, bench_calib,
              bench_e2e, bench_fingerprint, bench_chunk_compression, bench_firmware)

AVX2_SUFFIX = ".avx2"


def _all(name: str) -> bool:
    return True


SPEED: dict[str, tuple[Callable[[], Mapping[str, float]], Callable[[str], bool]]] = {
    "bench_driver": (bench_driver.run, _all),
    "bench_driver_publish": (bench_driver_publish.run, _all),
    "bench_recon_speed": (bench_recon_speed.run,
                          lambda name: name.startswith(("recon.ms.", "recon.hk_kernel."))
                          and name != "recon.hk_kernel.flop_per_pixel_iteration"),
    "bench_recon_publish": (bench_recon_publish.run, _all),
    "bench_e2e": (lambda: bench_e2e.run(demo_runs=0), lambda name: name != "e2e.mae_deg"),
    "bench_fingerprint": (bench_fingerprint.run_print_timing,
                          lambda name: name.endswith(".print_ms_median")),
}
"""The AVX2 pass: benchmark -> (what it runs, which of its figures are speed figures)."""


def avx2_names(figures: Mapping[str, float]) -> dict[str, float]:
    """The AVX2 pass's figures under their ``.avx2`` names."""
    return {f"{name}{AVX2_SUFFIX}": value for name, value in figures.items()}


def merge(kept: Mapping[str, object], native: Mapping[str, float],
          avx2: Mapping[str, float], machine: Mapping[str, object]) -> dict[str, object]:
    """results.json: the figures kept from the file (``soak.*``), the native figures, the
    AVX2 pass's as ``<name>.avx2`` and the ``machine.*`` entries."""
    return {**kept, **native, **avx2_names(avx2), **machine}


def run_native() -> dict[str, float]:
    """Every benchmark in this process; their tables printed."""
    results: dict[str, float] = {}
    for bench in BENCHMARKS:
        print(f"\n## {bench.__name__}: {bench.__doc__.splitlines()[0]}", flush=True)
        figures = bench.run()
        print_figures(figures)
        results.update(figures)
    return results


def run_speed_pass() -> dict[str, float]:
    """The speed benchmarks (:data:`SPEED`) in this process; their speed figures."""
    results: dict[str, float] = {}
    for name, (run, is_speed) in SPEED.items():
        print(f"\n## {name} (AVX2 pass)", flush=True)
        figures = {k: v for k, v in run().items() if is_speed(k)}
        print_figures(figures)
        results.update(figures)
    return results


def run_avx2(env: Mapping[str, str]) -> dict[str, float]:
    """The AVX2 pass in a new process with ``env``: the kernels compiled for its target
    first (outside every timed region), then :func:`run_speed_pass`; its figures."""
    subprocess.run([sys.executable, "-m", "fingerps_recon.photometric.kernel_warm_up"],
                   env=dict(env), check=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "avx2.json"
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--speed-pass-to",
                        str(out)], env=dict(env), check=True)
        return json.loads(out.read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="bench/results.json")
    parser.add_argument("--no-avx2", action="store_true",
                        help="skip the AVX2 pass (the native figures only)")
    parser.add_argument("--speed-pass-to", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.speed_pass_to is not None:  # the AVX2 pass's process (run_avx2)
        args.speed_pass_to.write_text(json.dumps(run_speed_pass()))
        return 0
    switches = simd_env.avx2_switches()
    machine = simd_env.machine_figures(switches)
    for name, value in machine.items():
        print(f"  {name:<42}  {value}")
    native = run_native()
    avx2: dict[str, float] = {}
    if not args.no_avx2:
        print("\n# AVX2 pass: " + " ".join(f"{k}={v}" for k, v in switches.items()
                                          if k != "NUMBA_CPU_FEATURES")
              + " NUMBA_CPU_FEATURES=<the host's, AVX-512 off>", flush=True)
        avx2 = run_avx2(simd_env.avx2_env())
    out = Path(args.out)
    # Figures of benchmarks run on their own (make soak) are kept; every other is this run's.
    kept = {k: v for k, v in (json.loads(out.read_text()) if out.is_file() else {}).items()
            if k.startswith(SEPARATE_PREFIXES)}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(merge(kept, native, avx2, machine), indent=2, sort_keys=True)
                   + "\n")
    print(f"\nwrote {len(native)} native and {len(avx2)} AVX2 figures to {args.out}")
    if avx2:
        _print_pairs(native, avx2)
    return 0


def _print_pairs(native: Mapping[str, float], avx2: Mapping[str, float]) -> None:
    """Each speed figure natively and in the AVX2 pass, side by side."""
    width = max(len(k) for k in avx2)
    print(f"  {'figure':<{width}}  {'native':>12}  {'avx2':>12}")
    for name, value in avx2.items():
        print(f"  {name:<{width}}  {native.get(name, float('nan')):12.3f}  {value:12.3f}")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
