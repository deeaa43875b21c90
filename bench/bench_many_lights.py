"""Many lights offline: offline_recon on a 96-light DiLiGenT-layout ball vs plain least squares.

Usage (tools/ros_env.sh sourced): ``python bench/bench_many_lights.py [--repeats N]``.

The object (no DiLiGenT data is needed, none is downloaded): :func:`write_ball` renders a
Lambertian ball into a DiLiGenT-layout folder as DiLiGenT's "ball" is laid out: 96 16-bit
colour PNGs of 612 x 512 px, ``filenames.txt``, ``light_directions.txt`` (an 8 x 12 grid of
LEDs on a plane in front of the object, as DiLiGenT's rig: directions up to ~38 degrees from
the camera axis), ``light_intensities.txt`` (one RGB intensity per LED, 0.6-1.4),
``mask.png`` (the ball, radius 71 px: ~15 800 px as DiLiGenT's 15 791) and ``Normal_gt.mat``.
Each image is e_k rho max(0, n . l_k) per channel (attached shadows: every light leaves part
of the ball dark) plus seeded Gaussian noise of 0.2 % of full scale, clipped to 16 bit.

Both solvers are timed on the same loaded :class:`~fingerps_recon.offline.diligent_folder.
PhotometricDataset`, alternately in one process (so that the machine's load falls on both),
after one warm-up each; medians of ``--repeats`` runs:

- ours: offline_recon's reconstruction (``offline_recon._reconstruct``: the pipeline with
  the folder's mask, Lambertian model, orthographic camera); its ``prepare`` (burst checks,
  saturation, mask) + ``lambert`` (the solve with per-pixel shadow and saturation
  selection) timings, which the issue's target is about; ``total`` (also the calibration's
  checks and the orthographic integration of the depth) beside them;
- plain: ``numpy.linalg.lstsq`` of the mask's pixels' (K, N) intensities, gathered from the
  (K, H, W) images by the mask (the gather is timed: ours reads the same images), against
  the (K, 3) lights scaled by the intensities, all pixels at once (as RobustPhotometric-
  Stereo's L2 solver); n = b / |b|. No shadow handling: the values of the attached shadows
  (zeros and noise) enter the fit. Beside it the quickest plain solve, the same gather and
  ``pinv(L) @ I`` (LAPACK's lstsq is slow for many right-hand sides).

Then the mean angular errors against the true normals over the mask (pixels without a
normal left out). ``run()`` returns ``many_lights.ms.ours`` (prepare + lambert),
``many_lights.ms.ours_total``, ``many_lights.ms.plain`` (lstsq), ``many_lights.ms.pinv``,
``many_lights.ratio`` (ours / plain), ``many_lights.ratio_pinv`` and
``many_lights.deg.ours`` / ``many_lights.deg.plain``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from fingerps_recon.offline.diligent_folder import PhotometricDataset, load_diligent_folder
from fingerps_recon.offline.offline_recon import _reconstruct
from fingerps_recon.photometric.angular_error import angular_error_deg
from fingerps_recon.photometric.pipeline import Model

RUNS = 21
SIZE = (512, 612)  # DiLiGenT's images: 612 x 512 px (H, W)
RADIUS_PX = 71.0
GRID = (8, 12)  # DiLiGenT's 96 LEDs: 8 rows x 12 columns on a plane in front of the object
NOISE = 0.002  # of full scale
FULL_SCALE = 65535.0


def ball_lights() -> np.ndarray:
    """(96, 3) unit directions, PS frame: an 8 x 12 grid of LEDs on the plane z = 1, spaced
    so that the outermost are ~38 degrees from the camera axis (DiLiGenT's spread)."""
    y, x = np.meshgrid(np.linspace(0.45, -0.45, GRID[0]), np.linspace(-0.65, 0.65, GRID[1]),
                       indexing="ij")
    lights = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)
    return lights / np.linalg.norm(lights, axis=1, keepdims=True)


def write_ball(folder: Path, *, seed: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Render the ball into the DiLiGenT-layout ``folder`` (see the module docstring);
    return its true normals (H, W, 3) and mask (H, W)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    h, w = SIZE
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2 + 20.5) / RADIUS_PX, -(v - h / 2 + 10.5) / RADIUS_PX  # off centre
    r2 = x * x + y * y
    mask = r2 < 1.0
    normals = np.where(mask[..., None],
                       np.stack([x, y, np.sqrt(np.clip(1.0 - r2, 0.0, None))], axis=-1), 0.0)
    lights = ball_lights()
    intensities = rng.uniform(0.6, 1.4, (len(lights), 3))
    rho = np.array([0.8, 0.6, 0.7])  # RGB
    names = [f"{i + 1:03d}.png" for i in range(len(lights))]
    for name, light, e in zip(names, lights, intensities, strict=True):
        shading = np.clip(normals @ light, 0.0, None)
        rgb = shading[..., None] * (e * rho * 0.55 * FULL_SCALE)
        rgb += rng.normal(0.0, NOISE * FULL_SCALE, rgb.shape)
        frame = np.clip(np.rint(rgb), 0, FULL_SCALE).astype(np.uint16)[..., ::-1]  # BGR
        assert cv2.imwrite(str(folder / name), frame)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_intensities.txt", intensities)
    assert cv2.imwrite(str(folder / "mask.png"), mask.astype(np.uint8) * 255)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normals})
    return normals, mask


def plain_least_squares(data: PhotometricDataset, *, pinv: bool = False) -> np.ndarray:
    """(H, W, 3) float64 normals of ``numpy.linalg.lstsq`` (or ``pinv(L) @ I``) over the
    mask's pixels, all at once, no shadow handling (see the module docstring)."""
    lights = data.lights_ps if data.intensities is None else (
        data.lights_ps * data.intensities[:, None])
    values = data.images[:, data.mask]  # (K, N)
    b = (np.linalg.pinv(lights) @ values if pinv
         else np.linalg.lstsq(lights, values, rcond=None)[0])  # (3, N)
    normals = np.zeros((*data.mask.shape, 3))
    normals[data.mask] = (b / np.linalg.norm(b, axis=0)).T
    return normals


@dataclass(frozen=True)
class ManyLightsReport:
    pixels: int
    lights: int
    ours_ms: float
    ours_total_ms: float
    prepare_ms: float
    lambert_ms: float
    plain_ms: float
    pinv_ms: float
    ours_deg: float
    plain_deg: float

    @property
    def ratio(self) -> float:
        return self.ours_ms / self.plain_ms

    @property
    def ratio_pinv(self) -> float:
        return self.ours_ms / self.pinv_ms


def measure(repeats: int = RUNS) -> ManyLightsReport:
    with tempfile.TemporaryDirectory() as tmp:
        truth, mask = write_ball(Path(tmp) / "ball")
        data = load_diligent_folder(Path(tmp) / "ball")

    def ours():
        return _reconstruct(data, model=Model.LAMBERT, pixel_size=1.0, enhance=False, w=7,
                            k=2.5)

    rec, plain = ours(), plain_least_squares(data)  # warm-up
    plain_least_squares(data, pinv=True)
    prepare, lambert, total, plain_ms, pinv_ms = [], [], [], [], []
    for _ in range(repeats):
        rec = ours()
        prepare.append(rec.timings_ms["prepare"])
        lambert.append(rec.timings_ms["lambert"])
        total.append(rec.timings_ms["total"])
        t0 = time.perf_counter()
        plain = plain_least_squares(data)
        plain_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        plain_least_squares(data, pinv=True)
        pinv_ms.append((time.perf_counter() - t0) * 1e3)
    both = np.add(prepare, lambert)
    return ManyLightsReport(
        pixels=int(mask.sum()), lights=int(data.images.shape[0]),
        ours_ms=float(np.median(both)), ours_total_ms=float(np.median(total)),
        prepare_ms=float(np.median(prepare)), lambert_ms=float(np.median(lambert)),
        plain_ms=float(np.median(plain_ms)), pinv_ms=float(np.median(pinv_ms)),
        ours_deg=float(np.nanmean(angular_error_deg(rec.normals_ps, truth, mask=mask))),
        plain_deg=float(np.nanmean(angular_error_deg(plain, truth, mask=mask))))


def run(repeats: int = RUNS) -> dict[str, float]:
    report = measure(repeats)
    _print(report, repeats)
    return {"many_lights.ms.ours": report.ours_ms,
            "many_lights.ms.ours_total": report.ours_total_ms,
            "many_lights.ms.plain": report.plain_ms, "many_lights.ms.pinv": report.pinv_ms,
            "many_lights.ratio": report.ratio, "many_lights.ratio_pinv": report.ratio_pinv,
            "many_lights.deg.ours": report.ours_deg, "many_lights.deg.plain": report.plain_deg}


def _print(report: ManyLightsReport, repeats: int) -> None:
    print(f"96-light DiLiGenT-layout ball: {report.lights} lights x {report.pixels} px, "
          f"medians of {repeats} runs")
    print(f"  ours  (offline_recon reconstruct.prepare + .lambert): {report.ours_ms:7.1f} ms "
          f"(prepare {report.prepare_ms:.1f} + lambert {report.lambert_ms:.1f}; whole "
          f"reconstruct {report.ours_total_ms:.1f})   mean error {report.ours_deg:.3f} deg")
    print(f"  plain (mask gather + numpy lstsq):                    {report.plain_ms:7.1f} ms"
          f"{'':44}mean error {report.plain_deg:.3f} deg")
    print(f"  plain (mask gather + pinv(L) @ I):                    {report.pinv_ms:7.1f} ms")
    print(f"  ratio ours / plain: {report.ratio:.2f} (target <= 2); ours / pinv "
          f"{report.ratio_pinv:.2f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=RUNS)
    args = parser.parse_args(argv)
    run(max(3, args.repeats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
