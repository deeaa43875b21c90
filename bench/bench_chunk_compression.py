"""The recorder's chunk compression: zstd level 1 (what fingerps writes,
``sessions/zstd_level.py``, as ``ros2 bag record`` does) against level 3 (the mcap Python
writer's own) and lz4, on one burst's session data from the simulated rig.

Usage (tools/ros_env.sh sourced): ``python bench/bench_chunk_compression.py``.

The data: what the recorder writes per burst with its defaults, as raw arrays (the CDR
framing around them is a few bytes): the burst's 7 images twice (``burst`` and ``frames``),
and recon_node's outputs with HK (normals, depth, albedo, points with intensity, the normal
map). Cut into the recorder's 4 MiB chunks and compressed one by one, ``RUNS`` times.
Figures: ``recorder.chunk_mb_per_burst``; per codec ``recorder.<codec>_ms_per_burst`` (median
of the runs, one core) and ``recorder.<codec>_ratio`` (uncompressed / compressed bytes).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import lz4.frame
import numpy as np
import zstandard

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_recon_speed import _burst, _node_calibration
from figures_report import print_figures

from fingerps_driver.simulation import RigConfig, SimulatedRig
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import (
    Model,
    ReconstructionOptions,
    reconstruct_prepared,
)
from fingerps_recon.sessions.session_bag import DEFAULT_CHUNK_SIZE

RUNS = 7
CODECS: dict[str, Callable[[bytes], bytes]] = {
    "zstd1": lambda data: zstandard.ZstdCompressor(level=1).compress(data),
    "zstd3": lambda data: zstandard.ZstdCompressor(level=3).compress(data),
    "lz4": lambda data: lz4.frame.compress(data),
}


def session_bytes() -> bytes:
    """One burst's recorded arrays (see the module docstring)."""
    rig = SimulatedRig(RigConfig())
    burst = _burst(rig)
    options = ReconstructionOptions(model=Model.HK, enhance=True)
    r = reconstruct_prepared(burst.images, _node_calibration(rig, burst, options),
                             full_scale=burst.full_scale, options=options)
    points = np.concatenate([r.points_optical, r.point_albedo[:, None]], axis=1)
    arrays = (burst.images, burst.images, r.normals_ps, r.depth_m, r.albedo,
              points.astype(np.float32), normal_map_rgb(r.enhanced_ps, mask=r.mask))
    return b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)


def run(runs: int = RUNS) -> dict[str, float]:
    data = session_bytes()
    chunks = [data[i:i + DEFAULT_CHUNK_SIZE] for i in range(0, len(data), DEFAULT_CHUNK_SIZE)]
    figures = {"recorder.chunk_mb_per_burst": len(data) / 1e6}
    for name, compress in CODECS.items():
        times, size = [], 0
        for _ in range(runs):
            start = time.perf_counter()
            size = sum(len(compress(chunk)) for chunk in chunks)
            times.append(time.perf_counter() - start)
        figures[f"recorder.{name}_ms_per_burst"] = float(np.median(times)) * 1e3
        figures[f"recorder.{name}_ratio"] = len(data) / size
    return figures


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)
    print_figures(run())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
