"""Normal and depth accuracy of the Lambertian and HK solvers on the simulated rig.

Scenes: the rig's finger rendered with the HK skin model ("hkfinger", A = 45, the paper's
finger constants) and with a Lambertian one ("lambertscene"), each image
``rig.noiseless(Scene.FINGER, [k])`` (fraction of full scale) plus seeded Gaussian noise of
0.5 %, 1 % and 2 % of full scale. Measurements <= 0 or >= 1 (saturated) are left out.

Light settings (what each solver is told about the lights; the rendering always uses the
true near LEDs, per-pixel directions from the true surface points and their inverse-square
and lobe fall-off):

- ``distant`` - "calibrated distant lights": one direction per LED,
  ``rig.light_directions_ps()`` (apex -> LED), and one relative intensity per LED,
  ``rig.light_intensities()`` (the lighting field at the apex), standing in for the
  mirror-sphere calibration's result (paper Sec. 3.1). No flat-field correction.
- ``distant_ff`` - the same directions, and the images divided by the flat field: the
  rig's noiseless white-target render W_k (paper Eq. 11, what the flat-field calibration
  measures; its 1 % paper texture included) divided by the target's cosine l_k . z for the
  distant direction, so that the corrected images are in white-target units (intensities 1).
  This is the paper's own pipeline.
- ``near`` - "near lights": per pixel, the direction from the surface point to LED k with
  the surface point assumed on the plane z = 0.09 m (the working distance) along the
  pixel's ray -- computed from the camera matrix and ``rig.led_positions_optical`` (what a
  calibration that triangulates the LED positions gives), NOT from the true surface -- and
  per-pixel intensities from the flat field, W_k / (l_k . z) with l_k that plane's direction
  (the irradiance of LED k on the plane, inverse square and lobe included). The images are
  not divided (their noise stays uniform; the solvers weight by the intensities).
- ``near_refined`` - ``near`` refined once with each solver's own result: its normals
  integrated to depth (``integrate_normals``, the nearest point at the working distance),
  the per-pixel directions recomputed from the LED positions to those points and the
  flat-field irradiance moved from the plane to them by the inverse-square law (the change
  of the LED lobe neglected); then solved again (HK warm-started). Calibration data and the
  solver's own estimate only.
- ``oracle`` (1 % noise, HK finger only; a diagnosis, not a calibration): the TRUE per-pixel
  directions and irradiance at the true surface points, to show the noise floor.

Both solvers get the same images and usable-measurement mask; the Lambertian solver
(paper Eq. 3) gets per-pixel lights for ``near`` (``solve_lambertian`` if it accepts them,
else the same least squares per pixel here), the HK solver (paper Eq. 6-7, A fitted) starts
from the Lambertian result and is given perspective views (minus each pixel's ray, exact
whatever the depth). Solver mask: the true finger silhouette.

Figures: mean and median angular error of the normals (degrees) inside the finger mask
eroded by 3 pixels; RMS depth error (micrometres) after ``integrate_normals`` (orthographic,
pixel size = working distance / f) against the true depth, mean offset removed; the
ridge visibility (``ridge_visibility``) of the HK normals before and after the ridge
enhancement of Eq. 12 (w = 7, k = 2.5). The headline keys (``recon.mae_deg.<solver>.
<scene>_1pct``, ``recon.ridge_visibility.*``) use the ``near`` setting: the most accurate
one that uses the calibration data alone (``near_refined`` also uses the solver's own
result, a reconstruction step the pipeline does not have); every setting is in the extra
keys (``...<scene>_<noise>.<setting>``).

Run: ``python bench/bench_recon_accuracy.py`` (prints a table); ``run()`` returns the
figures for bench/run_all.py.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from fingerps_driver.simulation import (
    Reflectance,
    RigConfig,
    Scene,
    SimulatedRig,
    SkinReflectance,
)
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.hk_solver import solve_hk
from fingerps_recon.photometric.lambertian import solve_lambertian
from fingerps_recon.photometric.normal_transform import enhance_ridges
from fingerps_recon.photometric.ridge_visibility import ridge_visibility
from fingerps_recon.surface.back_projection import height_to_distance
from fingerps_recon.surface.integration import integrate_normals

NOISES = (0.005, 0.01, 0.02)
SETTINGS = ("distant", "distant_ff", "near")
HEADLINE = "near"
SCENES = {"hkfinger": Reflectance.HK, "lambertscene": Reflectance.LAMBERT}
BORDER_PX = 3
SEED = 0


@dataclass(frozen=True)
class Lights:
    """What a solver is told about the lights, and the images' flat-field divisor."""

    directions: np.ndarray  # (K, 3) or (K, H, W, 3), PS frame
    intensities: np.ndarray | None  # (K,) or (K, H, W), or None
    divisor: np.ndarray | None  # (K, H, W) the images are divided by, or None


@dataclass(frozen=True)
class Outcome:
    """Accuracy of one solution."""

    mean_deg: float
    median_deg: float
    depth_rms_um: float
    normals: np.ndarray
    valid: np.ndarray


def _noise_tag(noise: float) -> str:
    return f"{noise * 100:g}pct".replace(".", "p")


def _pixel_rays(rig: SimulatedRig) -> np.ndarray:
    """(H, W, 3) rays (u - cx, v - cy, f) / f in the optical frame, z = 1."""
    k = rig.camera_matrix
    h, w = rig.camera.height, rig.camera.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], axis=-1)


def _light_settings(rig: SimulatedRig, white: np.ndarray) -> dict[str, Lights]:
    """The three calibrated light settings of the module docstring."""
    rays = _pixel_rays(rig)
    distant = rig.light_directions_ps()
    plane = rig.config.finger.apex_optical_m[2] * rays  # surface assumed on z = 0.09 m
    near = rig.led_positions_optical[:, None, None, :] - plane[None]
    near = optical_to_ps(near / np.linalg.norm(near, axis=-1, keepdims=True))
    return {
        "distant": Lights(distant, rig.light_intensities(), None),
        "distant_ff": Lights(distant, None, white / distant[:, 2, None, None]),
        "near": Lights(near, (white / near[..., 2]).astype(np.float32), None),
    }


def _oracle(rig: SimulatedRig) -> Lights:
    """TRUE per-pixel directions and irradiance at the true surface points (diagnosis)."""
    points = rig.finger_points_optical()
    inside = np.isfinite(points[..., 2])
    k = rig.led_count
    directions = np.zeros((k, *inside.shape, 3))
    directions[..., 2] = 1.0
    irradiance = np.ones((k, *inside.shape))
    for led in range(k):
        directions[led][inside] = optical_to_ps(rig.leds.directions_optical(points[inside], led))
        irradiance[led][inside] = rig.leds.irradiance(points[inside], led)
    return Lights(directions, (irradiance * rig.sensor.exposure_gain).astype(np.float32), None)


def _lambertian(images: np.ndarray, lights: Lights, mask: np.ndarray,
                usable: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lambertian photometric stereo (Eq. 3): (normals, albedo, valid)."""
    if lights.directions.ndim == 2:
        res = solve_lambertian(np.where(usable, images, 0.0), lights.directions,
                               intensities=lights.intensities, mask=mask)
        return res.normals, res.albedo, res.valid
    try:  # the library's solver, once it takes per-pixel lights
        res = solve_lambertian(np.where(usable, images, 0.0), lights.directions,
                               intensities=lights.intensities, mask=mask)
        return res.normals, res.albedo, res.valid
    except FingerpsReconError:
        pass
    # b = rho n = (sum_k l l^T)^-1 sum_k l I over the usable lights, per pixel.
    k, h, w = images.shape
    idx = np.flatnonzero(mask)
    lgt = lights.directions.reshape(k, h * w, 3)[:, idx]
    if lights.intensities is not None:
        lgt = lgt * np.broadcast_to(lights.intensities, images.shape).reshape(k, h * w)[
            :, idx, None]
    val = images.reshape(k, h * w)[:, idx]
    use = usable.reshape(k, h * w)[:, idx].astype(np.float64)
    gram = np.einsum("kn,kni,knj->nij", use, lgt, lgt)
    rhs = np.einsum("kn,kni,kn->ni", use, lgt, val)
    ok = (use.sum(axis=0) >= 3) & (np.linalg.det(gram) > 1e-9)
    b = np.zeros_like(rhs)
    b[ok] = np.linalg.solve(gram[ok], rhs[ok][..., None])[..., 0]
    rho = np.linalg.norm(b, axis=1)
    ok &= rho > 0
    normals = np.zeros((h * w, 3), np.float32)
    albedo = np.zeros(h * w, np.float32)
    valid = np.zeros(h * w, bool)
    normals[idx[ok]] = b[ok] / rho[ok, None]
    albedo[idx[ok]] = rho[ok]
    valid[idx[ok]] = True
    return normals.reshape(h, w, 3), albedo.reshape(h, w), valid.reshape(h, w)


def _score(normals: np.ndarray, valid: np.ndarray, truth: object, evaluate: np.ndarray,
           pixel_size_m: float, working_distance_m: float) -> Outcome:
    err = angular_error_deg(normals, truth.normals_ps, mask=evaluate & valid)
    finite = err[np.isfinite(err)]
    inside = truth.mask & valid
    height = integrate_normals(np.where(inside[..., None], normals, 0.0), mask=inside,
                               pixel_size_m=pixel_size_m)
    depth = height_to_distance(height, working_distance_m=working_distance_m)
    diff = (depth - truth.depth_m)[evaluate & valid].astype(np.float64)
    diff -= diff.mean()
    return Outcome(float(finite.mean()), float(np.median(finite)),
                   float(np.sqrt(np.mean(diff**2)) * 1e6), normals, valid)


def _refine(rig: SimulatedRig, plane: Lights, normals: np.ndarray, valid: np.ndarray,
            mask: np.ndarray, geometry: tuple[float, float]) -> Lights:
    """The ``near`` lights refined once with a solver's own normals (``near_refined``)."""
    pixel_size, working = geometry
    inside = mask & valid
    height = integrate_normals(np.where(inside[..., None], normals, 0.0), mask=inside,
                               pixel_size_m=pixel_size)
    # Depth along the optical axis, the nearest point (the apex) at the working distance.
    depth = np.where(inside, working + (np.nanmax(height[inside]) - height), working)
    rays = _pixel_rays(rig)
    leds = rig.led_positions_optical[:, None, None, :]
    towards = leds - depth[..., None] * rays[None]
    distance = np.linalg.norm(towards, axis=-1)
    plane_distance = np.linalg.norm(leds - working * rays[None], axis=-1)
    return Lights(
        optical_to_ps(towards / distance[..., None]),
        (plane.intensities * (plane_distance / distance) ** 2).astype(np.float32), None,
    )


def _solve_both(images: np.ndarray, usable: np.ndarray, lights: tuple[Lights, Lights],
                views: np.ndarray, truth: object, evaluate: np.ndarray,
                geometry: tuple[float, float], start: object = None) -> dict[str, object]:
    """Lambertian, then HK (from the Lambertian result, or warm from ``start``); lights =
    (the Lambertian solver's, the HK solver's)."""
    normals, albedo, valid = _lambertian(images, lights[0], truth.mask, usable)
    if start is None:
        init_n, init_a, init_v = normals, albedo, valid
    else:
        init_n, init_a, init_v = start.normals, start.albedo, start.valid
    clock = time.perf_counter()
    hk = solve_hk(images, lights[1].directions, mask=init_v & truth.mask, init_normals=init_n,
                  init_albedo=init_a, views=views, intensities=lights[1].intensities,
                  usable=usable)
    seconds = time.perf_counter() - clock
    return {
        "lambert": _score(normals, valid, truth, evaluate, *geometry),
        "hk": _score(hk.normals, hk.valid, truth, evaluate, *geometry),
        "lambert_raw": (normals, valid), "hk_raw": hk, "seconds": seconds,
    }


def run(verbose: bool = False) -> dict[str, float]:
    rng = np.random.default_rng(SEED)
    figures: dict[str, float] = {}
    rows: list[str] = []

    def record(scene: str, noise: float, name: str, out: dict[str, object]) -> None:
        tag = f"{scene}_{_noise_tag(noise)}.{name}"
        lam, hk, res = out["lambert"], out["hk"], out["hk_raw"]
        for solver, score in (("lambert", lam), ("hk", hk)):
            figures[f"recon.mae_deg.{solver}.{tag}"] = score.mean_deg
            figures[f"recon.median_deg.{solver}.{tag}"] = score.median_deg
            figures[f"recon.depth_rms_um.{solver}.{tag}"] = score.depth_rms_um
        figures[f"recon.hk_scale.{tag}"] = res.scale
        figures[f"recon.hk_iterations.{tag}"] = float(res.iterations)
        figures[f"recon.hk_ms.{tag}"] = out["seconds"] * 1e3
        rows.append(
            f"  {scene:12s} {noise * 100:4.1f}% {name:12s} "
            f"{lam.mean_deg:6.2f} {lam.median_deg:6.2f} {lam.depth_rms_um:7.1f} | "
            f"{hk.mean_deg:6.2f} {hk.median_deg:6.2f} {hk.depth_rms_um:7.1f} | "
            f"{hk.mean_deg / lam.mean_deg:5.2f} {res.scale:7.2f} {res.iterations:3d} "
            f"{out['seconds'] * 1e3:6.0f}"
        )
        if name == HEADLINE:
            for solver in ("lambert", "hk"):
                figures[f"recon.mae_deg.{solver}.{scene}_{_noise_tag(noise)}"] = figures[
                    f"recon.mae_deg.{solver}.{tag}"]

    for scene, reflectance in SCENES.items():
        rig = SimulatedRig(RigConfig(skin=SkinReflectance(model=reflectance)))
        clean = np.stack([rig.noiseless(Scene.FINGER, [k]) for k in range(rig.led_count)])
        white = np.stack([rig.noiseless(Scene.WHITE_TARGET, [k]) for k in range(rig.led_count)])
        truth = rig.finger_truth()
        evaluate = scipy.ndimage.binary_erosion(truth.mask, iterations=BORDER_PX)
        working = float(rig.config.finger.apex_optical_m[2])
        geometry = (working / float(rig.camera_matrix[0, 0]), working)
        rays = _pixel_rays(rig)
        views = optical_to_ps(-rays / np.linalg.norm(rays, axis=-1, keepdims=True))
        settings = _light_settings(rig, white)
        if scene == "hkfinger":
            ref = _score(truth.normals_ps, truth.mask, truth, evaluate, *geometry)
            figures["recon.depth_rms_um.truth_normals"] = ref.depth_rms_um
            figures["recon.ridge_visibility.truth"] = ridge_visibility(truth.normals_ps,
                                                                       mask=truth.mask)
            rows.append(f"  integrating the TRUE normals: depth RMS {ref.depth_rms_um:.1f} um "
                        "(orthographic integration of a perspective view)")
        cases = [(noise, name, settings[name]) for noise in NOISES for name in SETTINGS]
        if scene == "hkfinger":
            cases.append((0.01, "oracle", _oracle(rig)))
        for noise, name, lights in cases:
            noisy = clean + noise * rng.standard_normal(clean.shape)
            usable = (noisy > 0) & (noisy < 1.0)
            images = (noisy if lights.divisor is None else noisy / lights.divisor).astype(
                np.float32)
            out = _solve_both(images, usable, (lights, lights), views, truth, evaluate,
                              geometry)
            record(scene, noise, name, out)
            if name == "near":
                # Each solver refines the lights with its own normals, then solves again.
                refined = (
                    _refine(rig, lights, *out["lambert_raw"], truth.mask, geometry),
                    _refine(rig, lights, out["hk_raw"].normals, out["hk_raw"].valid,
                            truth.mask, geometry),
                )
                record(scene, noise, "near_refined", _solve_both(
                    images, usable, refined, views, truth, evaluate, geometry,
                    start=out["hk_raw"]))
            if scene == "hkfinger" and noise == 0.01 and name == HEADLINE:
                hk = out["hk_raw"]
                inner = truth.mask & hk.valid
                figures["recon.ridge_visibility.before"] = ridge_visibility(hk.normals,
                                                                            mask=inner)
                enhanced = enhance_ridges(hk.normals, w=7, k=2.5, mask=inner)
                figures["recon.ridge_visibility.after"] = ridge_visibility(enhanced, mask=inner)
                lam_normals, lam_valid = out["lambert_raw"]
                figures["recon.ridge_visibility.before_lambert"] = ridge_visibility(
                    lam_normals, mask=truth.mask & lam_valid)
    if verbose:
        print("scene        noise setting      | Lambertian: mean median depth | "
              "HK: mean median depth | HK/L   A  it  ms")
        print("                                     (deg)  (deg)   (um)       (deg)  (deg)   (um)")
        print("\n".join(rows))
        print("  ridge visibility (HK normals, hkfinger 1 %, near): before "
              f"{figures['recon.ridge_visibility.before']:.4f}, after Eq. 12 (w 7, k 2.5) "
              f"{figures['recon.ridge_visibility.after']:.4f}; Lambertian normals "
              f"{figures['recon.ridge_visibility.before_lambert']:.4f}; true normals "
              f"{figures['recon.ridge_visibility.truth']:.4f}")
    return figures


def main() -> int:
    start = time.perf_counter()
    figures = run(verbose=True)
    print(f"\n{len(figures)} figures in {time.perf_counter() - start:.0f} s; headline:")
    for key in ("recon.mae_deg.hk.hkfinger_1pct", "recon.mae_deg.lambert.hkfinger_1pct",
                "recon.mae_deg.hk.lambertscene_1pct", "recon.mae_deg.lambert.lambertscene_1pct",
                "recon.ridge_visibility.before", "recon.ridge_visibility.after"):
        print(f"  {key:42s} {figures[key]:8.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
