"""offline_recon: photometric stereo of a folder in the DiLiGenT layout, without ROS.

Usage::

    ros2 run fingerps_recon offline_recon FOLDER --out DIR [--model lambert|hk]
        [--w W] [--k K] [--pixel-size METRES] [--shadow-threshold V] [--saturation V]

FOLDER holds ``filenames.txt``, the PNG images it lists (8 or 16 bit, grey or colour),
``light_directions.txt`` (unit vectors, x right, y up, z towards the camera) and optionally
``light_intensities.txt`` (3 or 1 numbers a row), ``mask.png`` and ``Normal_gt.mat`` /
``normal_gt.npy`` (see ``fingerps_recon.offline.diligent_folder``).

Colour to grey: with three-channel intensities (as DiLiGenT), each channel is divided by its
intensity and the channels are averaged; otherwise colour images become Rec. 601 luma
(0.299 R + 0.587 G + 0.114 B). Without ``mask.png`` the pipeline's own finger mask is used.

The camera is orthographic: heights are integrated with the pixel size (--pixel-size
metres per pixel; by default 1, so heights are in pixel units).

Outputs in DIR:

- ``normals.npy``  (H, W, 3) float32 unit normals in the frame of the light directions,
  zeros outside the mask (never ridge-enhanced)
- ``normals_enhanced.npy``  (H, W, 3) float32, only with --w/--k (paper Eq. 12)
- ``albedo.npy``  (H, W) float32, PNG units per unit light intensity, zeros outside
- ``depth.npy``  (H, W) float32 height along +z (towards the camera), zero mean over the
  mask, metres (pixel units without --pixel-size), NaN outside
- ``normal_map.png``  RGB (n + 1) / 2 of the normals (the enhanced ones with --w/--k)
- ``fingerprint.png``  the rolled-equivalent print (`fingerps_recon.surface.rolled_print`): grey,
  ridges dark on white, 500 ppi, with the resolution in the PNG's ``pHYs`` chunk
  (19 685 pixels per metre); only with --pixel-size (it needs the metric scale), and only
  when the reconstruction can be unrolled (else report.json says why)
- ``fingerprint.wsq``  the same print as a WSQ file (`fingerps_recon.records.wsq_image`:
  NIST's codec, 0.75 bits per pixel, 500 ppi), checked by decoding it again; beside
  ``fingerprint.png`` whenever the codec gives the print back (else report.json says why)
- ``fingerprint.fmr``  its ISO/IEC 19794-2:2005 minutiae record (NBIS's minutiae,
  `fingerps_recon.records.iso_minutiae_record`), when NBIS finds minutiae
- ``fingerprint.an2``  its ANSI/NIST-ITL 1-2011 transaction: Type-1, Type-14 (the WSQ image)
  and Type-9 (the minutiae) (`fingerps_recon.records.ansi_nist_transaction`), with the
  folder's name as 1.009 TCN; report.json gives each record's size, or why it was not made,
  and the print's NFIQ 2
- ``cloud.ply``  one point a mask pixel in the camera optical frame (x right, y down, z away
  from the camera): x = (u - cx) s, y = (v - cy) s, z = -height, with albedo as
  ``intensity`` and the normals (optical frame)
- ``report.json``  counts, levels, timings and the ground-truth error when there is one

Bad input: one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError, RolledPrintError
from fingerps_recon.offline.diligent_folder import (
    DEFAULT_SHADOW_FRACTION,
    PhotometricDataset,
    load_diligent_folder,
)
from fingerps_recon.photometric.angular_error import angular_error_deg, summarize_angular_error
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import (
    Model,
    Projection,
    Reconstruction,
    ReconstructionOptions,
    reconstruct,
)
from fingerps_recon.records.print_records import make_print_records
from fingerps_recon.surface.ply import write_ply
from fingerps_recon.surface.png_resolution import png_with_resolution
from fingerps_recon.surface.rolled_print import rolled_print
from fingerps_ros.command_line import CommandLineTool

_DEFAULTS = ReconstructionOptions()
_PROG = "offline_recon"
TOOL = CommandLineTool(_PROG, bad_input=(FingerpsReconError,), failed=(OSError,),
                       failed_context="cannot write the outputs: ")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon offline_recon``; returns the exit code."""
    return TOOL.main(_parser(), run, argv)


def run(args: argparse.Namespace) -> int:
    """Read the folder, reconstruct, write the outputs and the summary."""
    t0 = time.perf_counter()
    model = Model(args.model)
    hk_solver = "fingerps_recon.photometric.hk_solver"
    if model is Model.HK and importlib.util.find_spec(hk_solver) is None:
        raise FingerpsReconError(
            "the HK solver is not available in this build; use --model lambert")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise FingerpsReconError(f"--out {out} exists and is not a folder")
    enhance = args.w is not None or args.k is not None
    w = _DEFAULTS.w if args.w is None else args.w
    k = _DEFAULTS.k if args.k is None else args.k
    pixel_size = 1.0 if args.pixel_size is None else args.pixel_size

    data = load_diligent_folder(args.folder, shadow_level=args.shadow_threshold,
                                saturation_level=args.saturation)
    t_load = time.perf_counter()
    rec = _reconstruct(data, model=model, pixel_size=pixel_size, enhance=enhance, w=w, k=k)
    t_rec = time.perf_counter()

    mask = rec.mask
    normals = rec.normals_ps
    albedo = rec.albedo
    height = rec.height_m
    t_depth = time.perf_counter()
    shown = normals
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FingerpsReconError(f"--out {out}: cannot create it ({exc.strerror})") from None
    written = ["normals.npy", "albedo.npy", "depth.npy", "normal_map.png", "cloud.ply"]
    np.save(out / "normals.npy", normals)
    if enhance:
        shown = np.where(mask[..., None], rec.enhanced_ps, 0.0).astype(np.float32)
        np.save(out / "normals_enhanced.npy", shown)
        written.insert(1, "normals_enhanced.npy")
    np.save(out / "albedo.npy", albedo)
    np.save(out / "depth.npy", height.astype(np.float32))
    rgb = normal_map_rgb(shown, mask=mask)
    if not cv2.imwrite(str(out / "normal_map.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{out / 'normal_map.png'}: OpenCV could not write it")
    _write_cloud(out / "cloud.ply", height, normals, albedo, mask, pixel_size=pixel_size)
    fingerprint = _write_fingerprint(out / "fingerprint.png", height, normals, mask,
                                     pixel_size=args.pixel_size)
    if fingerprint["made"]:
        written.append("fingerprint.png")
        written.extend(name for name, record in fingerprint["records"].items()
                       if isinstance(record, dict) and record["made"])
    t_write = time.perf_counter()

    report = {
        "folder": str(Path(args.folder).resolve()),
        "model": model.value,
        "images": len(data.names),
        "height": int(data.images.shape[1]),
        "width": int(data.images.shape[2]),
        "bit_depth": data.bit_depth,
        "colour_conversion": data.conversion.value,
        "intensities": data.intensities is not None,
        "shadow_threshold": data.shadow_level,
        "saturation": data.saturation_level,
        "mask_source": "mask.png" if data.mask is not None else "pipeline finger mask",
        "mask_pixels": int(data.mask.sum()) if data.mask is not None else None,
        "valid_pixels": int(mask.sum()),
        "pixel_size": pixel_size,
        "depth_unit": "m" if args.pixel_size is not None else "px",
        "enhancement": {"w": w, "k": k} if enhance else None,
        "normal_gt": _evaluate(data, normals, mask),
        "fingerprint": fingerprint,
        "timings_ms": {
            "load": (t_load - t0) * 1e3,
            "reconstruct": (t_rec - t_load) * 1e3,
            **{f"reconstruct.{name}": ms for name, ms in rec.timings_ms.items()},
            "depth": (t_depth - t_rec) * 1e3,
            "write": (t_write - t_depth) * 1e3,
            "total": (time.perf_counter() - t0) * 1e3,
        },
        "outputs": [*written, "report.json"],
    }
    (out / "report.json").write_text(json.dumps(_json_safe(report), indent=2) + "\n")
    print(_summary(report, out))
    return 0


def _reconstruct(data: PhotometricDataset, *, model: Model, pixel_size: float,
                 enhance: bool, w: int, k: float) -> Reconstruction:
    """Call the pipeline with an orthographic camera of ``pixel_size`` and the folder's mask."""
    _, height, width = data.images.shape
    camera_matrix = np.array([[1.0, 0.0, (width - 1) / 2.0],
                              [0.0, 1.0, (height - 1) / 2.0],
                              [0.0, 0.0, 1.0]])
    # The loader has set every saturated pixel to full scale: a fraction of 1 finds them.
    options = ReconstructionOptions(
        model=model, projection=Projection.ORTHOGRAPHIC,
        shadow_fraction=data.shadow_level / data.full_scale, saturation_fraction=1.0,
        enhance=enhance, w=w, k=k, working_distance_m=pixel_size)
    return reconstruct(data.images, lights_ps=data.lights_ps, camera_matrix=camera_matrix,
                       full_scale=data.full_scale, intensities=data.intensities,
                       mask=data.mask, options=options)


ORTHOGRAPHIC_DISTANCE_M = 10.0
"""Working distance of the pinhole camera that stands in for the orthographic one when the
print is unrolled: at 10 m a 5 mm deep finger changes the scale by 0.05 %."""


def _write_fingerprint(path: Path, height: np.ndarray, normals: np.ndarray, mask: np.ndarray,
                       *, pixel_size: float | None) -> dict:
    """Write the 500 ppi rolled print (PNG) and its exchange records beside it
    (``records.print_records``); return what report.json says of them."""
    if pixel_size is None:
        return {"made": False, "reason": "needs --pixel-size (metres per pixel): a 500 ppi "
                "print needs the metric scale"}
    h, w = mask.shape
    focal = ORTHOGRAPHIC_DISTANCE_M / pixel_size
    camera_matrix = np.array([[focal, 0.0, (w - 1) / 2.0], [0.0, focal, (h - 1) / 2.0],
                              [0.0, 0.0, 1.0]])
    depth = np.where(mask, ORTHOGRAPHIC_DISTANCE_M - height.astype(np.float64), np.nan)
    try:
        made = rolled_print(depth, mask=mask, camera_matrix=camera_matrix, normals_ps=normals)
    except RolledPrintError as exc:
        return {"made": False, "reason": str(exc)}
    path.write_bytes(png_with_resolution(made.image, made.ppi))
    records = make_print_records(made.image, transaction_control=path.parent.resolve().name)
    records.write(path.parent)
    return {"made": True, "ppi": made.ppi, "width_px": int(made.image.shape[1]),
            "height_px": int(made.image.shape[0]), "area_mm2": made.area_mm2,
            "strain_rms": made.strain_rms, "coherence": made.coherence,
            "records": records.report()}


def _write_cloud(path: Path, height: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                 mask: np.ndarray, *, pixel_size: float) -> None:
    """One point a mask pixel, orthographic, in the optical frame (see the docstring)."""
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    points = np.stack([(cols - (w - 1) / 2.0) * pixel_size,
                       (rows - (h - 1) / 2.0) * pixel_size,
                       -height[rows, cols]], axis=1)
    write_ply(path, points.astype(np.float32), intensity=albedo[rows, cols],
              normals=ps_to_optical(normals[rows, cols]))


def _evaluate(data: PhotometricDataset, normals: np.ndarray, mask: np.ndarray) -> dict | None:
    """Angular error against the folder's ground truth, inside its mask (or ours)."""
    if data.normal_gt is None:
        return None
    region = (data.mask if data.mask is not None else mask)
    region = region & (np.linalg.norm(data.normal_gt, axis=2) > 0)
    errors = angular_error_deg(normals, data.normal_gt, mask=region)
    stats = summarize_angular_error(errors)
    return {"file": data.normal_gt_file, "mean_deg": stats.mean, "median_deg": stats.median,
            "p95_deg": stats.p95, "pixels": stats.count,
            "pixels_without_normal": int(region.sum()) - stats.count}


def _json_safe(value: object) -> object:
    """NaN and infinities as null; numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_json_safe(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _summary(report: dict, out: Path) -> str:
    t = report["timings_ms"]
    mask = (f"mask {report['mask_pixels']} px (mask.png)" if report["mask_pixels"] is not None
            else "no mask.png: the pipeline's finger mask")
    lines = [
        f"{_PROG}: {report['images']} images {report['width']}x{report['height']} "
        f"{report['bit_depth']}-bit ({report['colour_conversion']}), model {report['model']}",
        f"  {mask}, valid normals {report['valid_pixels']} px",
    ]
    gt = report["normal_gt"]
    if gt is not None:
        lines.append(
            f"  angular error vs {gt['file']}: mean {gt['mean_deg']:.3f} deg, median "
            f"{gt['median_deg']:.3f} deg over {gt['pixels']} px "
            f"({gt['pixels_without_normal']} mask px without a normal)")
    fp = report["fingerprint"]
    lines.append(f"  fingerprint.png: {fp['width_px']}x{fp['height_px']} px at {fp['ppi']:g} ppi, "
                 f"{fp['area_mm2']:.0f} mm2" if fp["made"] else
                 f"  no fingerprint.png: {fp['reason']}")
    if fp["made"]:
        records = fp["records"]
        lines.append(f"  NFIQ 2: {records['nfiq2']}, minutiae: {records['minutiae']}")
        for name, rec in records.items():
            if isinstance(rec, dict):
                lines.append(f"  {name}: {rec['bytes']} bytes" if rec["made"]
                             else f"  no {name}: {rec['reason']}")
    lines.append(f"  time: load {t['load']:.0f} ms, reconstruct {t['reconstruct']:.0f} ms, "
                 f"depth {t['depth']:.0f} ms, write {t['write']:.0f} ms")
    lines.append(f"  wrote {', '.join(report['outputs'])} to {out}")
    return "\n".join(lines)


def _odd_patch(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 3 or value % 2 == 0:
        raise argparse.ArgumentTypeError(f"{value} must be an odd integer >= 3")
    return value


def _number(minimum: float, *, strict: bool):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            bound = ">" if strict else ">="
            raise argparse.ArgumentTypeError(f"{text} must be a finite number {bound} {minimum:g}")
        return value
    return parse


def _parser() -> argparse.ArgumentParser:
    shadow = ", ".join(f"{bits}-bit {frac * 100:g}%% of full scale = {frac * (2**bits - 1):g}"
                       for bits, frac in DEFAULT_SHADOW_FRACTION.items())
    parser = argparse.ArgumentParser(
        prog=_PROG,
        description="Photometric stereo of a folder in the DiLiGenT layout: normals, albedo, "
                    "depth and a point cloud. Colour images become grey by one rule: with "
                    "three-channel light_intensities.txt each channel is divided by its "
                    "intensity and the channels are averaged (DiLiGenT); otherwise Rec. 601 "
                    "luma 0.299 R + 0.587 G + 0.114 B. Bad input: one line on stderr, exit 2.",
        epilog="Outputs: normals.npy (H,W,3 float32, frame of the light directions, zeros "
               "outside the mask), normals_enhanced.npy (with --w/--k), albedo.npy, depth.npy "
               "(height towards the camera, NaN outside), normal_map.png, cloud.ply, "
               "report.json. With Normal_gt.mat or normal_gt.npy in the folder the angular "
               "error inside the mask is printed.")
    parser.add_argument("folder", help="folder with filenames.txt, light_directions.txt, the "
                                       "images, and optionally light_intensities.txt, "
                                       "mask.png (else the pipeline's finger mask), "
                                       "Normal_gt.mat")
    parser.add_argument("--out", required=True, help="output folder (created if missing)")
    parser.add_argument("--model", choices=[m.value for m in Model], default=Model.LAMBERT.value,
                        help="reflectance model: lambert (Lambertian PS) or hk (simplified "
                             "Hanrahan-Krueger skin model); default lambert")
    parser.add_argument("--w", type=_odd_patch, default=None,
                        help=f"ridge enhancement patch size, odd (paper Eq. 12); enhancement "
                             f"is off unless --w or --k is given; default {_DEFAULTS.w}")
    parser.add_argument("--k", type=_number(0.0, strict=False), default=None,
                        help=f"ridge enhancement gain >= 0; default {_DEFAULTS.k}")
    parser.add_argument("--pixel-size", type=_number(0.0, strict=True), default=None,
                        metavar="METRES",
                        help="metres per pixel on the object (orthographic): depth.npy and "
                             "cloud.ply in metres; default 1, i.e. in pixel units")
    parser.add_argument("--shadow-threshold", type=_number(0.0, strict=False), default=None,
                        metavar="VALUE",
                        help="PNG values at or below this are shadow and left out; default "
                             f"by bit depth ({shadow})")
    parser.add_argument("--saturation", type=_number(0.0, strict=True), default=None,
                        metavar="VALUE",
                        help="PNG values at or above this in any channel are saturated and "
                             "left out; default the full scale (255 or 65535)")
    return parser


if __name__ == "__main__":
    raise SystemExit(main())
