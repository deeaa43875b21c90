"""Run every fingerps benchmark, print their tables, write bench/results.json.

results.json is one flat JSON object of name -> number; each benchmark adds its names
(the ``soak.*`` figures of ``make soak`` are kept).
Usage (after ``make build``, with tools/ros_env.sh sourced): ``python bench/run_all.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_calib
import bench_driver
import bench_driver_publish
import bench_e2e
import bench_fingerprint
import bench_many_lights
import bench_recon_accuracy
import bench_recon_publish
import bench_recon_speed
from figures_report import print_figures

SEPARATE_PREFIXES = ("soak.",)
"""Figures of benchmarks not in ``make bench`` (``make soak``), kept when it rewrites the file."""

BENCHMARKS = (bench_driver, bench_driver_publish, bench_recon_speed, bench_recon_publish,
              bench_recon_accuracy, bench_many_lights, bench_calib, bench_e2e,
              bench_fingerprint)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="bench/results.json")
    args = parser.parse_args(argv)
    results: dict[str, float] = {}
    for bench in BENCHMARKS:
        print(f"\n## {bench.__name__}: {bench.__doc__.splitlines()[0]}")
        figures = bench.run()
        print_figures(figures)
        results.update(figures)
    out = Path(args.out)
    # Figures of benchmarks run on their own (make soak) are kept; every other is this run's.
    kept = {k: v for k, v in (json.loads(out.read_text()) if out.is_file() else {}).items()
            if k.startswith(SEPARATE_PREFIXES)}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({**kept, **results}, indent=2, sort_keys=True) + "\n")
    print(f"\nwrote {len(results)} figures to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
