"""Calibration accuracy on the simulated rig: light directions, sphere centre, flat field, normals.

Light directions, against ground truth, per LED:

- one placement: the sphere at each of four positions, at three noise levels; truth = the
  direction from the sphere's true specular point to the LED (what a single placement
  measures: a near LED seen from the sphere);
- combined: the four placements of each noise level, LEDs triangulated, directions from the
  finger apex (the reference point, where the finger is); truth = apex -> true LED, which is
  also what the reconstruction's "true lights" are (``SimulatedRig.light_directions_ps``).

Sphere centre: distance of the fitted centre from the true one. LED positions: distance of
the triangulated position from the true one.

Flat field: the maps from the 8-bit white target (with its paper texture and noise) correct
a textureless, noiseless rendering of the target; residual non-uniformity = std/mean of the
corrected image over the whole field of view, per LED (the worst is reported).

Normals: Lambertian reconstruction of a finger burst (flat-field corrected, the flat field's
relative intensities) with the true lights and with calibrated lights; mean angular error
against the true normals.

Usage: ``python bench/bench_calib.py`` (after ``source tools/ros_env.sh``), or through
bench/run_all.py.
"""

from __future__ import annotations

import time

import numpy as np

from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_calib.lights.led_triangulation import Placement, combine_placements
from fingerps_calib.lights.sphere_calibration import calibrate_lights
from fingerps_driver.simulation import (
    MirrorSphere,
    RigConfig,
    Scene,
    SensorModel,
    SimulatedRig,
    WhiteTarget,
)
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.pipeline import reconstruct

#: Sphere centres (optical frame, metres); the whole 4 mm ball stays in view.
POSITIONS = {
    "centre (2, -1.5, 94) mm": (2.0e-3, -1.5e-3, 0.094),
    "left (-5.5, 2, 94) mm": (-5.5e-3, 2.0e-3, 0.094),
    "right far (5, 2.5, 98) mm": (5.0e-3, 2.5e-3, 0.098),
    "near (-4, -2.5, 88) mm": (-4.0e-3, -2.5e-3, 0.088),
}
#: The sensor of each noise level.
NOISE = {
    "12 bit, low noise": SensorModel(bit_depth=12, full_well_e=20000.0, read_noise_e=5.0),
    "8 bit (default)": SensorModel(),
    "8 bit, 1/4 well, 4x read": SensorModel(full_well_e=2500.0, read_noise_e=40.0),
}


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _sphere_images(rig: SimulatedRig, seed: int) -> np.ndarray:
    return rig.render_burst(Scene.SPHERE, seed=seed)


def _lights(rows: list[tuple[str, str, np.ndarray, float]], apex: np.ndarray
            ) -> tuple[dict[str, object], list[np.ndarray]]:
    """Single placements and combinations at every noise level; table rows appended."""
    all_errors, centre_errors, position_errors, seconds = [], [], [], []
    combined_by_noise = {}
    for n_index, (noise, sensor) in enumerate(NOISE.items()):
        placements = []
        for p_index, (where, centre) in enumerate(POSITIONS.items()):
            rig = SimulatedRig(RigConfig(sphere=MirrorSphere(center_optical_m=centre),
                                         sensor=sensor))
            images = _sphere_images(rig, 1000 * n_index + 100 * p_index)
            t0 = time.perf_counter()
            result = calibrate_lights(images, camera_matrix=rig.camera_matrix,
                                      radius_m=rig.config.sphere.radius_m,
                                      saturation_level=rig.max_value(),
                                      require_whole_sphere=True,
                                      expected_distance_m=(0.063, 0.117))
            seconds.append(time.perf_counter() - t0)
            if not result.ok:
                raise RuntimeError(f"{noise}, {where}: {result.problems}")
            specular = np.stack([rig.sphere.specular_point(q)
                                 for q in rig.led_positions_optical])
            errors = _angles(result.directions_optical, rig.led_positions_optical - specular)
            centre_error = 1e3 * np.linalg.norm(result.sphere_center_optical_m - centre)
            rows.append((noise, f"one: {where}", errors, centre_error))
            all_errors.append(errors)
            centre_errors.append(centre_error)
            placements.append(Placement.from_result(result))
        combined = combine_placements(placements, reference_point_optical_m=apex)
        if not combined.ok:
            raise RuntimeError(f"{noise}: combination failed: {combined.problems}")
        truth = rig.led_positions_optical - apex
        errors = _angles(combined.directions_optical, truth)
        rows.append((noise, f"combined: {len(placements)} placements, from the apex", errors,
                     float("nan")))
        all_errors.append(errors)
        position_errors.append(1e3 * np.linalg.norm(
            combined.led_positions_optical_m - rig.led_positions_optical, axis=1))
        combined_by_noise[noise] = combined
    errors = np.concatenate(all_errors)
    figures = {
        "calib.light_err_deg.mean": float(errors.mean()),
        "calib.light_err_deg.max": float(errors.max()),
        "calib.sphere_center_err_mm.max": float(np.max(centre_errors)),
        "calib.led_position_err_mm.max": float(np.max(position_errors)),
        "calib.lights_s.median": float(np.median(seconds)),
    }
    return figures, combined_by_noise


def _flat_field(rig: SimulatedRig) -> tuple[dict[str, float], object]:
    white = rig.render_burst(Scene.WHITE_TARGET, seed=500)
    dark = rig.render(Scene.WHITE_TARGET, [], rng=np.random.default_rng(499))
    t0 = time.perf_counter()
    flat = flat_field_maps(white, dark=dark, saturation_level=rig.max_value())
    seconds = time.perf_counter() - t0
    plain = SimulatedRig(RigConfig(white_target=WhiteTarget(texture_amplitude=0.0)))
    before, after = [], []
    for k in range(rig.led_count):
        target = plain.noiseless(Scene.WHITE_TARGET, [k]).astype(np.float64)[2:-2, 2:-2]
        corrected = target / flat.portions[k][2:-2, 2:-2]
        before.append(100 * target.std() / target.mean())
        after.append(100 * corrected.std() / corrected.mean())
    print(f"\n  flat field: std/mean of the flat target per LED (%), before "
          f"{np.round(before, 1).tolist()}\n              after correction "
          f"{np.round(after, 2).tolist()}; fit residuals (%) "
          f"{np.round(100 * flat.fit_residuals, 2).tolist()}")
    return {"calib.flatfield_residual_pct": float(np.max(after)),
            "calib.flatfield_uncorrected_pct": float(np.max(before)),
            "calib.flat_field_s": seconds}, flat


def _normals(rig: SimulatedRig, flat, combined, single_ps: np.ndarray,
             axis_ps: np.ndarray) -> dict[str, float]:
    rng = np.random.default_rng(7)
    images = rig.render_burst(Scene.FINGER, rng=rng)
    dark = rig.render(Scene.FINGER, [], rng=rng)
    truth = rig.finger_truth()

    def mae(lights_ps: np.ndarray) -> float:
        result = reconstruct(images, lights_ps=lights_ps, camera_matrix=rig.camera_matrix,
                             full_scale=rig.max_value(), dark=dark,
                             intensities=flat.relative_intensities, portions=flat.portions)
        both = result.mask & truth.mask
        return float(angular_error_deg(result.normals_ps, truth.normals_ps)[both].mean())

    true_lights = mae(rig.light_directions_ps())
    calibrated = mae(combined.directions_ps)
    single = mae(single_ps)
    on_axis = mae(axis_ps)
    print(f"\n  normals' mean angular error (deg): true lights {true_lights:.3f}; calibrated "
          f"(combined, from the apex) {calibrated:.3f} (difference "
          f"{calibrated - true_lights:+.3f});\n  from a point on the axis at the working "
          f"distance, (0, 0, 90) mm: {on_axis:.3f}; one placement's directions (centre) "
          f"{single:.3f}")
    return {"calib.recon_mae_deg.true_lights": true_lights,
            "calib.recon_mae_deg.calibrated": calibrated,
            "calib.recon_mae_delta_deg": calibrated - true_lights,
            "calib.recon_mae_deg.single_placement": single}


def run() -> dict[str, float]:
    """Run the benchmark, print its tables, return the figures."""
    rig = SimulatedRig(RigConfig())
    apex = np.asarray(rig.config.finger.apex_optical_m, dtype=np.float64)
    rows: list[tuple[str, str, np.ndarray, float]] = []
    figures, combined_by_noise = _lights(rows, apex)
    n_led = rig.led_count
    header = (f"  {'noise':<26}{'sphere':<44}" + "".join(f"LED{k:<3}" for k in range(n_led))
              + "  mean   max  centre")
    print("\n  light-direction error (deg) per LED; sphere centre error (mm)")
    print(header)
    for noise, what, errors, centre_error in rows:
        centre = f"{centre_error:6.3f}" if np.isfinite(centre_error) else "     -"
        print(f"  {noise:<26}{what:<44}" + "".join(f"{e:<6.3f}" for e in errors)
              + f"{errors.mean():6.3f}{errors.max():6.3f}  {centre}")
    errors = np.concatenate([r[2] for r in rows])
    print(f"  all: mean {errors.mean():.3f} deg, worst {errors.max():.3f} deg (target <= 0.5 "
          "mean, <= 1 worst)")
    flat_figures, flat = _flat_field(rig)
    figures.update(flat_figures)
    default = combined_by_noise["8 bit (default)"]
    single = default.placements[0]  # the default sphere position
    axis = combine_placements(default.placements,
                              reference_point_optical_m=np.array([0.0, 0.0, 0.09]))
    figures.update(_normals(rig, flat, default, optical_to_ps(single.directions_optical),
                            axis.directions_ps))
    return figures


if __name__ == "__main__":
    for name, value in run().items():
        print(f"  {name:<40} {value:10.4f}")
