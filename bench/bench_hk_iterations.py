"""HK accuracy against iterations: the mean angular error of the normals after 0, 1, 2, ...
Levenberg–Marquardt iterations, with A held (every burst after the first) and fitted (a
first burst), on the simulated rig's finger against its true normals.

Usage (tools/ros_env.sh sourced): ``python bench/bench_hk_iterations.py``.

The standard simulated rig and the node's calibration (near lights from the LED positions,
white-target irradiance, perspective views; ``photometric.pipeline``), ``BURSTS`` bursts of
the finger with fresh noise. The first burst is solved with A fitted (converged: 50
iterations); its A is held for the others (``reconstruct_prepared(hk_initial_scale=...)``,
as recon_node does), each solved with every iteration count of ``HELD_ITERATIONS`` (tol 0:
each one done) and with the defaults (``ReconstructionOptions``: at most ``hk_iterations``,
stopped per chunk by ``hk_tol``). A first burst's solves with A fitted are measured at
``FITTED_ITERATIONS`` on the second burst. Figures (``recon.hk_iter.*``): the mean error in
degrees over the valid pixels (``mae_deg.held_<n>``, ``mae_deg.held_default``,
``mae_deg.fitted_<n>``), and with the defaults the most and the mean iterations a chunk
of pixels did (``held_default_iterations_max`` / ``_mean``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_recon_speed import _burst, _node_calibration

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.photometric import hk_passes_kernel
from fingerps_recon.photometric.pipeline import (
    Model,
    ReconstructionOptions,
    reconstruct_prepared,
)

BURSTS = 4
HELD_ITERATIONS = (0, 1, 2, 3, 5, 10)
FITTED_ITERATIONS = (2, 3, 5, 10, 50)


def _mae_deg(normals: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    cosine = np.clip(np.sum(normals[mask].astype(np.float64) * truth[mask], axis=1), -1, 1)
    return float(np.degrees(np.arccos(cosine)).mean())


def run() -> dict[str, float]:
    rig = SimulatedRig(RigConfig())
    burst = _burst(rig)
    truth = rig.finger_truth().normals_ps
    options = ReconstructionOptions(model=Model.HK)
    prepared = _node_calibration(rig, burst, options)
    bursts = [rig.render_burst(Scene.FINGER, seed=1000 * i) for i in range(BURSTS)]

    def solve(images: np.ndarray, held: float | None, **changes: float) -> object:
        return reconstruct_prepared(images, prepared, full_scale=burst.full_scale,
                                    options=dataclasses.replace(options, **changes),
                                    hk_initial_scale=held)

    held = solve(bursts[0], None, hk_iterations=50, hk_tol=0.0).hk_scale
    figures: dict[str, float] = {}
    for count in HELD_ITERATIONS:
        errors = [_mae_deg(r.normals_ps, truth, r.mask)
                  for r in (solve(b, held, hk_iterations=count, hk_tol=0.0) for b in bursts[1:])]
        figures[f"recon.hk_iter.mae_deg.held_{count}"] = float(np.mean(errors))
    # The defaults, and the iterations each chunk did (solve_held's per-chunk parts).
    done: list[np.ndarray] = []
    kernel = hk_passes_kernel.solve_held

    def counting(*args: object) -> None:
        kernel(*args)
        done.append(np.asarray(args[-1])[:, 2].copy())

    hk_passes_kernel.solve_held = counting
    try:
        errors = [_mae_deg(r.normals_ps, truth, r.mask)
                  for r in (solve(b, held) for b in bursts[1:])]
    finally:
        hk_passes_kernel.solve_held = kernel
    iterations = np.concatenate(done)
    figures["recon.hk_iter.mae_deg.held_default"] = float(np.mean(errors))
    figures["recon.hk_iter.held_default_iterations_max"] = float(iterations.max())
    figures["recon.hk_iter.held_default_iterations_mean"] = float(iterations.mean())
    for count in FITTED_ITERATIONS:
        result = solve(bursts[1], None, hk_iterations=count, hk_tol=0.0)
        figures[f"recon.hk_iter.mae_deg.fitted_{count}"] = _mae_deg(
            result.normals_ps, truth, result.mask)
    return figures


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)
    for name, value in run().items():
        print(f"  {name:<45} {value:8.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
