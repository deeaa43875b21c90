"""Reconstruction speed stage by stage: one simulated 659x493 burst of 7 images -> points.

Usage (tools/ros_env.sh sourced): ``python bench/bench_recon_speed.py [--repeats N]``.
Prints, for every stage, the median and the spread (interquartile range and min-max) over
N runs (default 15, at least 7) after one warm-up run, then the integration's accuracy
against the simulated rig's true depth. ``run()`` returns the medians as
``recon.ms.<stage>`` (``recon.ms.lambert_total``, and ``recon.ms.hk_solve`` and
``recon.ms.hk_total`` when ``photometric.hk_solver.solve_hk`` exists) and the accuracy
figures as ``recon.um.<name>``.

Every stage is run back to back after one warm-up run, but for host_reference,
pipeline_lambert, pipeline_hk and the two hk_kernel stages: their runs are taken in turn,
in ``SPREAD_BLOCKS`` blocks ``SPREAD_GAP_S`` s apart (each block warmed up by one untimed
run), so that their medians do not hang on the host's speed during one second.

Stages, in the order of the Lambertian path (burst -> point cloud), all on the standard
simulated rig (``fingerps_driver.simulation``), with the white-target flat field:

- flat_field: ``apply_flat_field`` of the uint8 burst (K x H x W float32 division).
- mask: ``finger_mask`` (brightest image, a percentile, opening, closing, components).
- lambertian: ``solve_lambertian`` with distant lights; lambertian_near: the same with
  per-pixel (K, H, W, 3) near-light directions (not part of the path).
- transform: ``enhance_ridges`` (Eq. 12, w = 7, k = 2.5).
- integration_fast / integration_exact: ``integrate_normals`` (orthographic) FAST / EXACT;
  integration_perspective(_exact): ``integrate_normals_perspective``.
- cloud: ``height_to_distance`` + ``depth_to_points``.
- lambert_total: flat_field + mask + lambertian + transform + integration_fast + cloud run
  back to back; lambert_total_perspective: the same with the perspective integration.
- host_reference: a fixed numpy job on every core at once (a thread each: product, square
  root and sum of two burst-sized float32 stacks), none of the project's code, timed in
  the same rounds as pipeline_lambert and pipeline_hk: the shared host's speed at those
  moments, beside which the pipeline figures are read.
- pipeline_prepare: ``fingerps_recon.photometric.pipeline.prepare_calibration`` for the demo's
  calibration (near lights from the LED positions, white-target irradiance, perspective
  views), its caches emptied: what recon_node does once per calibration and camera.
- pipeline_lambert / pipeline_hk: ``photometric.pipeline.reconstruct_prepared`` with that
  prepared calibration, as recon_node runs it per burst (perspective integration, ridge
  transform, points; HK: A held at the previous burst's refit, as recon_node does). The
  figures the real-time targets are about; ``recon.ms.lambert_total`` /
  ``recon.ms.hk_total`` are hand-chained stages.
- hk_solve / hk_total: ``solve_hk`` (10 iterations) from the Lambertian start, and the
  HK path (Lambertian path with the HK solve after the Lambertian one), distant lights.
- hk_kernel_0_iterations / hk_kernel_10_iterations: ``solve_hk`` with the pipeline's
  near-light inputs and A held at its fit (the solve of every burst after the first), 0 and
  10 iterations (tol 0); their difference over the iterations the chunks of pixels did on
  average (``HKResult.mean_iterations``: a chunk stops when its steps promise no decrease)
  is one LM iteration, from which ``recon.hk_kernel.*`` (flops counted in the kernel's
  source).

The figures of the last ``make bench`` are in ``bench/results.json`` (native, and ``.avx2``
with AVX-512 turned off); the README's real-time table quotes them.

BLAS does only the few 3 x 3 solves of the calibration here (the per-pixel solves are numba
kernels, the integration pocketfft and OpenCV), so OPENBLAS_CORETYPE, which selects an older,
slower OpenBLAS kernel on the machines that set it (see the environment notes), changes
little; the table's header prints it.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.photometric.finger_mask import finger_mask
from fingerps_recon.photometric.flat_field import apply_flat_field
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.lambertian import solve_lambertian
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_recon.surface.back_projection import depth_to_points, height_to_distance
from fingerps_recon.surface.integration import (
    IntegrationMethod,
    integrate_normals,
    integrate_normals_perspective,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures_report import parse_repeats
from simd_env import cpu_info, simd_lanes

RUNS = 15
MIN_RUNS = 7
KERNEL_ITERATIONS = 10
# Floating-point operations of one HK LM iteration with A held (the iteration every burst
# after the first runs: photometric/hk_passes_kernel.py solve_held), counted in the source
# (add, mul, fma = 2, div, sqrt, min/max each 1; loads, stores, selects, floor and integer
# ops not counted): per measurement (pixel x light) in model_sums (hk_model_kernel.py): c_i
# 5, lighting selects 2, 1/c_i 1, q 2, the exponent 2 and exp() 16, e p S 3, e c_i 1, A P 1,
# u 2, r 3, w_q 3, capped inverses 2, df/dc_r 4, df/dc_i 6, j1, j2 10, the 15 sums 30: 93.
# Per pixel: the candidate's step and normal (trial_state, hk_step_kernel.py) 33,
# view_terms 14, keep_better 30, steps 70, the predicted decrease 6: 153.
FLOPS_PER_MEASUREMENT = 93
FLOPS_PER_PIXEL = 153
WORKING_DISTANCE_M = 0.09
SHADOW_FRACTION = 0.02
MASK_THRESHOLD = 0.15
HK_ITERATIONS = 10
# The per-burst figures' runs are taken in blocks this far apart (_time_spread).
SPREAD_BLOCKS = 5
SPREAD_GAP_S = 4.0


@dataclass(frozen=True)
class StageTiming:
    """Wall-clock times of one stage over the repeated runs, milliseconds."""

    stage: str
    times_ms: tuple[float, ...]

    @property
    def median(self) -> float:
        return float(np.median(self.times_ms))

    @property
    def quartiles(self) -> tuple[float, float]:
        q1, q3 = np.percentile(self.times_ms, [25, 75])
        return float(q1), float(q3)


@dataclass(frozen=True)
class SpeedReport:
    """What :func:`measure` found: stage timings, accuracy figures and notes."""

    timings: tuple[StageTiming, ...]
    accuracy_um: dict[str, float]
    notes: tuple[str, ...]
    kernel: KernelRate | None = None


@dataclass(frozen=True)
class KernelRate:
    """How far one HK Levenberg–Marquardt iteration is from the machine's peak."""

    ms_per_iteration: float
    pixels: int
    lights: int
    flops_per_iteration: float   # counted in the kernel's source (FLOPS_PER_* below)
    gflops: float                # achieved
    peak_gflops: float           # the cores' float32 peak (peak_gflops())
    peak_description: str
    mean_iterations: float = float("nan")  # iterations the chunks did, of KERNEL_ITERATIONS

    @property
    def fraction_of_peak(self) -> float:
        return self.gflops / self.peak_gflops

    @property
    def line(self) -> str:
        return (f"HK kernel: {self.ms_per_iteration:.2f} ms per LM iteration for "
                f"{self.pixels} px x {self.lights} lights, "
                f"{self.flops_per_iteration / self.pixels:.0f} flop per pixel and iteration "
                f"-> {self.gflops:.1f} GFLOP/s = {100 * self.fraction_of_peak:.1f} % of the "
                f"cores' float32 peak {self.peak_gflops:.0f} GFLOP/s ({self.peak_description})")


@dataclass(frozen=True)
class _Burst:
    images: np.ndarray        # (K, H, W) uint8
    portions: np.ndarray      # (K, H, W) float32
    intensities: np.ndarray   # (K,)
    lights_ps: np.ndarray     # (K, 3)
    lights_near_ps: np.ndarray  # (K, H, W, 3) float32, from the true surface points
    camera_matrix: np.ndarray
    full_scale: float


def _burst(rig: SimulatedRig) -> _Burst:
    k = rig.led_count
    images = rig.render_burst(Scene.FINGER, seed=10)
    white = rig.render_burst(Scene.WHITE_TARGET, seed=200)
    white_dark = rig.render(Scene.WHITE_TARGET, [], rng=np.random.default_rng(199))
    flat = flat_field_maps(white, dark=white_dark)
    points = np.nan_to_num(rig.finger_points_optical(), nan=WORKING_DISTANCE_M)
    near = np.stack([optical_to_ps(rig.leds.directions_optical(points, i)) for i in range(k)])
    return _Burst(images=images, portions=flat.portions, intensities=flat.relative_intensities,
                  lights_ps=rig.light_directions_ps(), lights_near_ps=near.astype(np.float32),
                  camera_matrix=np.asarray(rig.camera_matrix), full_scale=rig.max_value())


from fingerps_recon.photometric.pipeline import (  # noqa: E402
    Model,
    PreparedCalibration,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)


def _node_calibration(rig: SimulatedRig, burst: _Burst,
                      options: ReconstructionOptions) -> PreparedCalibration:
    """The calibration recon_node prepares for ``burst`` (near lights from the LED positions,
    white-target irradiance, perspective views), with ``options``."""
    return prepare_calibration(
        burst.lights_ps, camera_matrix=burst.camera_matrix, shape=burst.images.shape[1:],
        intensities=burst.intensities, portions=burst.portions,
        led_positions_optical=rig.led_positions_optical, options=options)


def peak_gflops(env: Mapping[str, str] | None = None) -> tuple[float, str]:
    """The cores' float32 peak: cores x SIMD lanes x 2 FMA units x 2 flop x the nominal clock
    (``/proc/cpuinfo``), and how it was derived. The lanes are those of the run's numba
    target (``simd_env.simd_lanes``, environment ``env``, default ``os.environ``): 16 with
    AVX-512, 8 with AVX2 -- also in the AVX2 run on an AVX-512 machine, whose kernels are
    compiled without AVX-512 (bench/run_all.py)."""
    mhz = 0.0
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("cpu MHz"):
                    mhz = float(line.split(":", 1)[1])
                    break
    except OSError:
        pass
    lanes = simd_lanes(cpu_info()[1], env)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    ghz = mhz / 1e3 if mhz else float("nan")
    return (cores * lanes * 2 * 2 * ghz,
            f"{cores} cores x {lanes} float32 lanes x 2 FMA x 2 flop x {ghz:.2f} GHz")


def kernel_rate(ms_per_iteration: float, pixels: int, lights: int) -> KernelRate:
    """The HK kernel's achieved rate from the time of one iteration (see FLOPS_PER_*)."""
    flops = pixels * (lights * FLOPS_PER_MEASUREMENT + FLOPS_PER_PIXEL)
    peak, description = peak_gflops()
    return KernelRate(ms_per_iteration=ms_per_iteration, pixels=pixels, lights=lights,
                      flops_per_iteration=float(flops),
                      gflops=flops / (ms_per_iteration * 1e-3) / 1e9, peak_gflops=peak,
                      peak_description=description)


def _time(fn: Callable[[], object], repeats: int) -> tuple[object, tuple[float, ...]]:
    result = fn()  # warm-up (caches, allocator, FFT plans)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append((time.perf_counter() - start) * 1e3)
    return result, tuple(times)


def _time_spread(stages: Mapping[str, Callable[[], object]], repeats: int,
                 blocks: int = SPREAD_BLOCKS, gap_s: float = SPREAD_GAP_S
                 ) -> dict[str, tuple[object, tuple[float, ...]]]:
    """``repeats`` timed runs of each of ``stages``, taken in ``blocks`` blocks ``gap_s``
    apart: in each block one untimed run of every stage (warm caches, as back to back),
    then rounds of one timed run of each, in turn. A shared host's speed changes within
    minutes (README, Real time), so the samples of the per-burst figures come from several
    moments instead of one second, and stages timed in the same rounds saw the same host
    (``host_reference`` beside the pipeline; the 0- and 10-iteration kernel runs whose
    difference is one iteration's cost)."""
    results: dict[str, object] = {}
    times: dict[str, list[float]] = {name: [] for name in stages}
    for block in range(blocks):
        if block:
            time.sleep(gap_s)
        for name, fn in stages.items():
            results[name] = fn()
        for _ in range(repeats // blocks + (block < repeats % blocks)):
            for name, fn in stages.items():
                start = time.perf_counter()
                results[name] = fn()
                times[name].append((time.perf_counter() - start) * 1e3)
    return {name: (results[name], tuple(times[name])) for name in stages}


def _host_reference(planes: np.ndarray) -> float:
    """A fixed job of numpy alone (``recon.ms.host_reference``): on each of the process's
    cores (a thread each, numpy releases the GIL) a product, a square root and a sum over
    two burst-sized float32 stacks of its own, as memory-bound as the reconstruction's
    passes; the time until all are done. ``planes``: (cores, 2, K, H, W)."""
    def job(own: np.ndarray) -> float:
        out = np.multiply(own[0], own[1])
        np.sqrt(out, out=out)
        return float(out.sum(dtype=np.float64))

    others = [threading.Thread(target=job, args=(own,)) for own in planes[1:]]
    for thread in others:
        thread.start()
    total = job(planes[0])
    for thread in others:
        thread.join()
    return total


def _uncached_prepare(prepare: Callable[[Model], object], model: Model) -> object:
    """``prepare(model)`` with pixel_rays' caches of directions emptied first (as for a new
    calibration or camera)."""
    from fingerps_recon.photometric import pixel_rays

    pixel_rays._cached_lights.cache_clear()
    pixel_rays._cached_views.cache_clear()
    return prepare(model)


def _solve_hk() -> Callable | None:
    try:
        module = importlib.import_module("fingerps_recon.photometric.hk_solver")
    except ImportError:
        return None
    return getattr(module, "solve_hk", None)


def measure(repeats: int = RUNS) -> SpeedReport:
    """Time every stage ``repeats`` times on one simulated burst (see the module docstring)."""
    if repeats < MIN_RUNS:
        raise ValueError(f"repeats must be >= {MIN_RUNS} for a meaningful spread, got {repeats}")
    rig = SimulatedRig(RigConfig())
    burst = _burst(rig)
    truth = rig.finger_truth()
    k_mat = burst.camera_matrix
    pixel_size_m = WORKING_DISTANCE_M / float(k_mat[0, 0])
    shadow_level = SHADOW_FRACTION * burst.full_scale
    timings: list[StageTiming] = []
    notes: list[str] = []

    def stage(name: str, fn: Callable[[], object]) -> object:
        result, times = _time(fn, repeats)
        timings.append(StageTiming(name, times))
        return result

    def spread(stages: Mapping[str, Callable[[], object]]) -> dict[str, object]:
        measured = _time_spread(stages, repeats)
        timings.extend(StageTiming(name, times) for name, (_, times) in measured.items())
        return {name: result for name, (result, _) in measured.items()}

    stack = stage("flat_field", lambda: apply_flat_field(burst.images, burst.portions))
    saturation_level = float(stack.max()) + 1.0  # as the pipeline: nothing saturated here
    mask = stage("mask", lambda: finger_mask(stack, threshold=MASK_THRESHOLD))

    def lambertian(lights: np.ndarray):
        return solve_lambertian(stack, lights, intensities=burst.intensities, mask=mask,
                                shadow_level=shadow_level, saturation_level=saturation_level)

    lam = stage("lambertian", lambda: lambertian(burst.lights_ps))
    stage("lambertian_near", lambda: lambertian(burst.lights_near_ps))
    valid = lam.valid & mask
    normals = lam.normals
    stage("transform", lambda: enhance_ridges(normals, mask=valid))

    def orthographic(normals: np.ndarray, valid: np.ndarray, method: IntegrationMethod):
        height = integrate_normals(normals, mask=valid, pixel_size_m=pixel_size_m,
                                   method=method)
        return height_to_distance(height, working_distance_m=WORKING_DISTANCE_M)

    def perspective(normals: np.ndarray, valid: np.ndarray, method: IntegrationMethod):
        return integrate_normals_perspective(normals, mask=valid, camera_matrix=k_mat,
                                             working_distance_m=WORKING_DISTANCE_M,
                                             method=method)

    depth_fast = stage("integration_fast",
                       lambda: orthographic(normals, valid, IntegrationMethod.FAST))
    depth_exact = stage("integration_exact",
                        lambda: orthographic(normals, valid, IntegrationMethod.EXACT))
    depth_persp = stage("integration_perspective",
                        lambda: perspective(normals, valid, IntegrationMethod.FAST))
    depth_persp_exact = stage("integration_perspective_exact",
                              lambda: perspective(normals, valid, IntegrationMethod.EXACT))
    stage("cloud", lambda: depth_to_points(depth_fast, valid, camera_matrix=k_mat))

    def lambert_path(integrate: Callable) -> object:
        corrected = apply_flat_field(burst.images, burst.portions)
        m = finger_mask(corrected, threshold=MASK_THRESHOLD)
        res = solve_lambertian(corrected, burst.lights_ps, intensities=burst.intensities,
                               mask=m, shadow_level=shadow_level,
                               saturation_level=float(corrected.max()) + 1.0)
        v = res.valid & m
        enhance_ridges(res.normals, mask=v)
        depth = integrate(res.normals, v, IntegrationMethod.FAST)
        return depth_to_points(depth, v, camera_matrix=k_mat)

    stage("lambert_total", lambda: lambert_path(orthographic))
    stage("lambert_total_perspective", lambda: lambert_path(perspective))

    solve_hk = _solve_hk()
    if solve_hk is None:
        notes.append("hk_solve, hk_total: skipped, "
                     "fingerps_recon.photometric.hk_solver.solve_hk not found")
    else:
        usable = (stack > shadow_level) & (stack < saturation_level)

        def hk(normals: np.ndarray, albedo: np.ndarray, valid: np.ndarray, stack=stack,
               usable=usable):
            return solve_hk(stack, burst.lights_ps, mask=valid, init_normals=normals,
                            init_albedo=albedo, intensities=burst.intensities, usable=usable,
                            iterations=HK_ITERATIONS)

        def hk_path() -> object:
            corrected = apply_flat_field(burst.images, burst.portions)
            m = finger_mask(corrected, threshold=MASK_THRESHOLD)
            limit = float(corrected.max()) + 1.0
            res = solve_lambertian(corrected, burst.lights_ps, intensities=burst.intensities,
                                   mask=m, shadow_level=shadow_level, saturation_level=limit)
            ok = (corrected > shadow_level) & (corrected < limit)
            out = hk(res.normals, res.albedo, res.valid & m, stack=corrected, usable=ok)
            v = out.valid & res.valid & m
            n = np.where(v[..., None], out.normals, 0.0).astype(np.float32)
            enhance_ridges(n, mask=v)
            depth = orthographic(n, v, IntegrationMethod.FAST)
            return depth_to_points(depth, v, camera_matrix=k_mat)

        try:
            stage("hk_solve", lambda: hk(lam.normals, lam.albedo, valid))
            stage("hk_total", hk_path)
        except Exception as exc:  # another engineer's module, possibly mid-change
            notes.append(f"hk_solve, hk_total: skipped, solve_hk raised {exc!r}")

    # The node's own path, with the calibration the demo makes (near lights from the LED
    # positions, white-target irradiance, perspective, ridge transform): the calibration
    # prepared once (pipeline_prepare; recon_node does it when the calibration or the camera
    # changes), then pipeline.reconstruct_prepared per burst.
    def prepare(model: Model) -> object:
        return _node_calibration(rig, burst, ReconstructionOptions(model=model, enhance=True))

    # As recon_node: A held at the previous burst's refit (calibration_in_force.
    # PreparedCalibrations.hk_scale), here the A of a first, cold burst.
    last_scale: dict[Model, float | None] = {model: None for model in Model}

    def pipeline(model: Model) -> object:
        result = reconstruct_prepared(burst.images, prepared_for[model],
                                      full_scale=burst.full_scale,
                                      options=ReconstructionOptions(model=model, enhance=True),
                                      hk_initial_scale=last_scale[model])
        last_scale[model] = result.hk_scale
        return result

    # The host's speed at this moment, on a job of none of this project's code: a shared
    # host's speed changes by up to 2x within minutes (README), so a stage's figure is
    # read beside it.
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    reference = np.random.default_rng(1).uniform(
        0, 1, (cores, 2, *burst.images.shape)).astype(np.float32)
    stage("pipeline_prepare", lambda: _uncached_prepare(prepare, Model.HK))
    prepared_for = {model: prepare(model) for model in Model}
    spread({"host_reference": lambda: _host_reference(reference),
            "pipeline_lambert": lambda: pipeline(Model.LAMBERT),
            "pipeline_hk": lambda: pipeline(Model.HK)})

    # The HK kernel's rate: solve_hk with the pipeline's near-light inputs and A held at
    # its fit (as every burst after the first), 0 and KERNEL_ITERATIONS iterations (tol 0:
    # every iteration whose steps promise any decrease is done); the difference is the
    # cost of the iterations alone (the gathering and the start excluded).
    if solve_hk is not None:
        options = ReconstructionOptions(model=Model.HK)
        prepared = _node_calibration(rig, burst, options)
        stack = burst.images.astype(np.float32)
        usable_near = (stack > shadow_level) & (stack < saturation_level)
        lam_near = solve_lambertian(stack, prepared.lights, intensities=prepared.light_power,
                                    mask=mask, shadow_level=shadow_level,
                                    saturation_level=saturation_level)

        def hk_iterations(count: int, scale: float | None = None) -> object:
            return solve_hk(stack, prepared.lights, mask=lam_near.valid & mask,
                            init_normals=lam_near.normals, init_albedo=lam_near.albedo,
                            views=prepared.views, intensities=prepared.light_power,
                            usable=usable_near, iterations=count, tol=0.0, scale=scale)

        held = hk_iterations(KERNEL_ITERATIONS).scale

        solved = spread({
            "hk_kernel_0_iterations": lambda: hk_iterations(0, held),
            f"hk_kernel_{KERNEL_ITERATIONS}_iterations":
                lambda: hk_iterations(KERNEL_ITERATIONS, held),
        })[f"hk_kernel_{KERNEL_ITERATIONS}_iterations"]
        kernel_pixels = int(solved.valid.sum())

    if solve_hk is not None:
        medians = {t.stage: t.median for t in timings}
        # Chunks stop once their steps promise no decrease: divide by the iterations the
        # chunks did on average (the work done), not by the iterations asked for.
        per_iteration_ms = (medians[f"hk_kernel_{KERNEL_ITERATIONS}_iterations"]
                            - medians["hk_kernel_0_iterations"]) / solved.mean_iterations
        notes.append(f"HK kernel: {solved.mean_iterations:.2f} of {KERNEL_ITERATIONS} "
                     "iterations done on average over the chunks of pixels")
        rate = dataclasses.replace(
            kernel_rate(per_iteration_ms, kernel_pixels, burst.images.shape[0]),
            mean_iterations=solved.mean_iterations)
        notes.append(rate.line)
        kernel = rate
    else:
        kernel = None
    accuracy = _accuracy(truth, valid, depth_fast, depth_exact, depth_persp, depth_persp_exact,
                         normals=truth.normals_ps, camera_matrix=k_mat,
                         pixel_size_m=pixel_size_m)
    return SpeedReport(timings=tuple(timings), accuracy_um=accuracy, notes=tuple(notes),
                       kernel=kernel)


def _accuracy(truth, valid, depth_fast, depth_exact, depth_persp, depth_persp_exact, *,
              normals, camera_matrix, pixel_size_m) -> dict[str, float]:
    """Depth RMS errors (um) against the true depth, inside both masks.

    Orthographic depths with the best offset (the height's zero level is free), perspective
    depths with the best scale (depth from normals is known up to a scale); also from the
    true normals, which isolates the integration from the normals' own errors.
    """
    both = valid & truth.mask
    true_depth = truth.depth_m[both].astype(np.float64)

    def offset_rms(depth: np.ndarray) -> float:
        err = depth[both].astype(np.float64) - true_depth
        return float(np.sqrt(np.mean((err - err.mean()) ** 2)) * 1e6)

    def scale_rms(depth: np.ndarray) -> float:
        d = depth[both].astype(np.float64)
        scale = np.exp(np.mean(np.log(true_depth) - np.log(d)))
        return float(np.sqrt(np.mean((scale * d - true_depth) ** 2)) * 1e6)

    def diff_rms(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sqrt(np.mean((a[both].astype(np.float64) - b[both]) ** 2)) * 1e6)

    figures = {
        "depth_rms_ortho_fast": offset_rms(depth_fast),
        "depth_rms_ortho_exact": offset_rms(depth_exact),
        "ortho_fast_vs_exact_rms": diff_rms(depth_fast, depth_exact),
        "depth_rms_perspective_fast": scale_rms(depth_persp),
        "depth_rms_perspective_exact": scale_rms(depth_persp_exact),
        "perspective_fast_vs_exact_rms": diff_rms(depth_persp, depth_persp_exact),
    }
    m = truth.mask
    for method in IntegrationMethod:
        suffix = method.name.lower()
        height = integrate_normals(normals, mask=m, pixel_size_m=pixel_size_m, method=method)
        ortho = height_to_distance(height, working_distance_m=WORKING_DISTANCE_M)
        persp = integrate_normals_perspective(normals, mask=m, camera_matrix=camera_matrix,
                                              working_distance_m=WORKING_DISTANCE_M,
                                              method=method)
        figures[f"true_normals_depth_rms_ortho_{suffix}"] = offset_rms(ortho)
        figures[f"true_normals_depth_rms_perspective_{suffix}"] = scale_rms(persp)
    return figures


def run(repeats: int = RUNS) -> dict[str, float]:
    """Median stage times (``recon.ms.<stage>``) and accuracy (``recon.um.<name>``)."""
    report = measure(repeats)
    figures = {f"recon.ms.{t.stage}": t.median for t in report.timings}
    figures.update({f"recon.um.{name}": value for name, value in report.accuracy_um.items()})
    if report.kernel is not None:
        figures["recon.hk_kernel.ms_per_iteration"] = report.kernel.ms_per_iteration
        figures["recon.hk_kernel.flop_per_pixel_iteration"] = (
            report.kernel.flops_per_iteration / report.kernel.pixels)
        figures["recon.hk_kernel.gflops"] = report.kernel.gflops
        figures["recon.hk_kernel.peak_gflops"] = report.kernel.peak_gflops
        figures["recon.hk_kernel.fraction_of_peak"] = report.kernel.fraction_of_peak
        figures["recon.hk_kernel.mean_iterations"] = report.kernel.mean_iterations
    return figures


def _print(report: SpeedReport, repeats: int) -> None:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    coretype = os.environ.get("OPENBLAS_CORETYPE")
    print(f"recon speed: 659x493 burst of 7, {repeats} runs each, {os.cpu_count()} cores, "
          f"load average {load:.2f}, OPENBLAS_CORETYPE={coretype or 'unset'}, numba target "
          f"{os.environ.get('NUMBA_CPU_NAME', 'host')} ({simd_lanes(cpu_info()[1])} float32 "
          "lanes)")
    print(f"  {'stage':<30} {'median':>8} {'IQR':>17} {'min-max':>17}   (ms)")
    for t in report.timings:
        q1, q3 = t.quartiles
        print(f"  {t.stage:<30} {t.median:8.2f} {q1:8.2f}-{q3:<8.2f} "
              f"{min(t.times_ms):8.2f}-{max(t.times_ms):<8.2f}")
    for note in report.notes:
        print(f"  note: {note}")
    print("accuracy against the true depth (um RMS; ortho: best offset, perspective: best "
          "scale)")
    for name, value in report.accuracy_um.items():
        print(f"  {name:<45} {value:10.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    args = parse_repeats(parser, argv, runs=RUNS, min_runs=MIN_RUNS, what="runs per stage")
    _print(measure(args.repeats), args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
