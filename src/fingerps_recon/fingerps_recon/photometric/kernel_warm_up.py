"""Warming the compiled (numba) kernels of the reconstruction before the first burst.

The first call of a numba kernel in a process compiles it (tens of seconds on a small CPU)
or loads it from numba's on-disk cache (about a second); either would fall on the first
burst. :func:`warm_up_kernels` reconstructs a tiny synthetic burst through
:func:`photometric.pipeline.reconstruct_prepared` -- near and distant lights, the HK model
(A fitted, then held as for the bursts after the first), the dtypes a camera gives -- so
every kernel the pipeline calls is ready afterwards, and says how many were compiled and
how many loaded from the cache.

``make build`` runs this module (``python -m fingerps_recon.photometric.kernel_warm_up``)
so that the cache is filled during the build; ``recon_node`` calls :func:`warm_up_kernels` in its
worker at start. Where the cache is: numba's rule (``__pycache__`` beside the kernels'
sources when writable, else the user's cache directory, or ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import argparse
import importlib
import time
from dataclasses import dataclass

import numpy as np

from fingerps_recon.photometric.pipeline import (
    Model,
    Projection,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.surface import integration, print_kernel

# Modules holding numba kernels (cache=True), counted in the report.
KERNEL_MODULES = ("fingerps_recon.photometric.hk_model_kernel",
                  "fingerps_recon.photometric.hk_gather_kernel",
                  "fingerps_recon.photometric.hk_step_kernel",
                  "fingerps_recon.photometric.hk_passes_kernel",
                  "fingerps_recon.photometric.lambertian_kernel",
                  "fingerps_recon.photometric.normal_transform_kernel",
                  "fingerps_recon.surface.back_projection_kernel",
                  "fingerps_recon.surface.integration_cg_kernel",
                  "fingerps_recon.surface.integration_polynomial_kernel",
                  "fingerps_recon.surface.integration_rhs_kernel",
                  "fingerps_recon.surface.integration_solution_kernel",
                  "fingerps_recon.surface.integration_sum_kernel",
                  "fingerps_recon.surface.integration_topology_kernel",
                  "fingerps_recon.surface.print_kernel")
_SIZE = 40          # synthetic image side, pixels
_RADIUS = 16.0      # synthetic hemisphere radius, pixels
_LEDS = 7
_FOCAL = 3000.0


@dataclass(frozen=True)
class WarmUp:
    """What :func:`warm_up_kernels` did."""

    seconds: float
    compiled: int   # kernel versions compiled in this process so far
    loaded: int     # kernel versions loaded from numba's on-disk cache so far
    modules: tuple[str, ...]  # the kernel modules that could be imported

    @property
    def summary(self) -> str:
        """One line for a log: what happened and how long it took."""
        if not self.modules:
            return f"no compiled kernels available (numba missing), {self.seconds:.1f} s"
        if self.compiled:
            return (f"compiled {self.compiled} kernel version(s) in {self.seconds:.1f} s "
                    f"(first start; cached on disk for the next), loaded {self.loaded}")
        return f"loaded {self.loaded} compiled kernel version(s) from the cache in " \
               f"{self.seconds:.1f} s"


def warm_up_kernels() -> WarmUp:
    """Compile or load every kernel the pipeline uses by reconstructing a tiny synthetic
    burst (a Lambertian hemisphere under near and distant lights) with the HK model, the
    integration's (:func:`fingerps_recon.surface.integration.warm_up`: the burst's mask is
    one component, which leaves one kernel out) and the rolled print's
    (:func:`fingerps_recon.surface.print_kernel.warm_up`)."""
    start = time.perf_counter()
    print_kernel.warm_up()
    integration.warm_up()
    images, lights, leds, k_matrix, portions = _synthetic_burst()
    for led_positions in (leds, None):
        for model in (Model.HK, Model.LAMBERT):
            options = ReconstructionOptions(model=model, hk_iterations=2, enhance=True,
                                            projection=Projection.PERSPECTIVE)
            prepared = prepare_calibration(
                lights, camera_matrix=k_matrix, shape=images.shape[1:],
                intensities=np.ones(_LEDS), portions=portions,
                led_positions_optical=led_positions, options=options)
            # HK: a first burst fits A, the next ones hold it (recon_node's sequence).
            scale = None
            for _ in range(2 if model is Model.HK else 1):
                scale = reconstruct_prepared(images, prepared, full_scale=255.0,
                                             options=options, hk_initial_scale=scale).hk_scale
    compiled, loaded, modules = _cache_stats()
    return WarmUp(seconds=time.perf_counter() - start, compiled=compiled, loaded=loaded,
                  modules=modules)


def _cache_stats() -> tuple[int, int, tuple[str, ...]]:
    """(versions compiled, versions loaded from the cache, modules) over the kernels, each
    counted once (a kernel module imports the helpers it calls from another)."""
    compiled = loaded = 0
    modules: list[str] = []
    seen: set[int] = set()
    for name in KERNEL_MODULES:
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        modules.append(name)
        for obj in vars(module).values():
            stats = getattr(obj, "stats", None)
            if stats is not None and hasattr(stats, "cache_misses") and id(obj) not in seen:
                seen.add(id(obj))
                compiled += sum(stats.cache_misses.values())
                loaded += sum(stats.cache_hits.values())
    return compiled, loaded, tuple(modules)


def _synthetic_burst() -> tuple[np.ndarray, ...]:
    """(images (K, S, S) uint8, lights (K, 3), LED positions (K, 3) m, K (3, 3), portions)."""
    angles = 2.0 * np.pi * np.arange(_LEDS) / _LEDS
    leds = np.stack([0.04 * np.cos(angles), 0.04 * np.sin(angles), np.zeros(_LEDS)], axis=1)
    to_leds = np.array([0.0, 0.0, ReconstructionOptions().working_distance_m]) - leds
    lights = to_leds / np.linalg.norm(to_leds, axis=1, keepdims=True)
    lights[:, 1:] *= -1.0  # optical -> PS frame
    c = (_SIZE - 1) / 2.0
    v, u = np.mgrid[0:_SIZE, 0:_SIZE].astype(np.float64)
    x, y = (u - c) / _RADIUS, (c - v) / _RADIUS
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    normals = np.stack([x, y, z], axis=-1)
    shading = np.clip(np.einsum("kc,hwc->khw", lights, normals), 0.0, None)
    inside = (x * x + y * y) < 0.95
    images = np.where(inside, 20.0 + 200.0 * shading, 2.0).astype(np.uint8)
    k_matrix = np.array([[_FOCAL, 0.0, c], [0.0, _FOCAL, c], [0.0, 0.0, 1.0]])
    portions = np.full(images.shape, 0.9, dtype=np.float32)
    return images, lights, leds, k_matrix, portions


def main(argv: list[str] | None = None) -> int:
    """``python -m fingerps_recon.photometric.kernel_warm_up``: warm the kernel cache, print
    one line."""
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)
    print(f"fingerps_recon kernels: {warm_up_kernels().summary}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
