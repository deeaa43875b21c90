"""``calibrate_lights``: light directions from a folder of shiny-sphere images.

The folder holds one image of the sphere per LED, listed in ``filenames.txt`` (one file
name a line, in LED order; blank lines and ``#`` comments ignored), and optionally
``mask.png`` (the sphere's pixels non-zero). With ``--camera-info`` (a camera_info YAML,
e.g. from ``calibrate_camera``) and ``--radius`` the perspective method of the paper is used
(Sec. 3.1: sphere centre from the tangent rays, mirror reflection at the highlight); without
intrinsics, the classic orthographic chrome-sphere method (circle fitted to the silhouette,
view along the optical axis), as for public data sets such as DiLiGenT's.

Writes into ``--out`` (default: the folder):

- ``light_directions.txt``: one row per image, ``x y z`` in the DiLiGenT convention (x
  right, y up, z towards the camera), unit vectors; only when every check passed.
- ``light_calibration_report.yaml``: method, per image the direction, highlight and
  residual, the sphere fit and its residual, and the problems found.
- ``light_calibration.png``: the picture (sphere, silhouette, highlights, polar plot).

An existing light_directions.txt is not overwritten without ``--force`` (a data set's
folder usually ships its own). Exit status: 0 calibrated, 1 the calibration failed its
checks (see the report), 2 bad input (the message says what to fix).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from fingerps_calib.calibration_picture import (
    circle_outline,
    distort_points,
    lights_picture,
    sphere_outline,
    write_png,
)
from fingerps_calib.calibration_store import write_atomic
from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_yaml import load_camera_info
from fingerps_calib.lights.sphere_calibration import calibrate_lights, calibrate_lights_orthographic
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_ros.command_line import EXIT_FAILED, CommandLineTool, positive_number

DIRECTIONS_FILE = "light_directions.txt"
REPORT_FILE = "light_calibration_report.yaml"
PICTURE_FILE = "light_calibration.png"
TOOL = CommandLineTool("calibrate_lights", bad_input=(FingerpsCalibError,))


def read_sphere_folder(folder: Path, *, mask_path: Path | None = None
                       ) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """The images listed in ``folder/filenames.txt`` as (K, H, W), and the mask if any.

    Colour images are averaged to grey; the dtype of the files is kept (uint8, uint16).

    Raises
    ------
    FingerpsCalibError
        A missing or empty filenames.txt, a missing or unreadable image, images of
        different sizes, or a mask of another size.
    """
    listing = folder / "filenames.txt"
    try:
        names = [line.split("#", 1)[0].strip()
                 for line in listing.read_text(encoding="utf-8").splitlines()]
    except FileNotFoundError:
        raise FingerpsCalibError(
            f"{listing} does not exist: list the sphere images there, one file name a line "
            "in LED order") from None
    except OSError as exc:
        raise FingerpsCalibError(f"cannot read {listing}: {exc}") from exc
    names = [n for n in names if n]
    if not names:
        raise FingerpsCalibError(f"{listing} lists no image; give one file name per LED")
    images = []
    for name in names:
        image = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FingerpsCalibError(
                f"cannot read image {folder / name} (listed in {listing}): check the name "
                "and that it is a PNG, JPEG, BMP or TIFF file")
        if image.ndim == 3:
            image = np.round(image[:, :, :3].astype(np.float64).mean(axis=2)).astype(
                image.dtype)
        images.append(image)
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        listed = ", ".join(f"{n}: {im.shape[1]}x{im.shape[0]}"
                           for n, im in zip(names, images, strict=True))
        raise FingerpsCalibError(f"the images have different sizes ({listed}); use one camera")
    stack = np.stack(images)
    mask = None
    mask_path = mask_path if mask_path is not None else (
        folder / "mask.png" if (folder / "mask.png").exists() else None)
    if mask_path is not None:
        raw = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if raw is None:
            raise FingerpsCalibError(f"cannot read the mask {mask_path}")
        if raw.shape != stack.shape[1:]:
            raise FingerpsCalibError(
                f"the mask {mask_path} is {raw.shape[1]}x{raw.shape[0]}, the images "
                f"{stack.shape[2]}x{stack.shape[1]}; give a mask of the images' size")
        mask = raw > 0
    return names, stack, mask


def run(args: argparse.Namespace) -> int:
    """Calibrate, write the outputs, print a summary; return the exit status."""
    folder = Path(args.folder)
    out = Path(args.out) if args.out else folder
    if (out / DIRECTIONS_FILE).exists() and not args.force:
        raise FingerpsCalibError(
            f"{out / DIRECTIONS_FILE} exists (a data set's own?); pass --force to replace it "
            "or --out to write elsewhere")
    names, images, mask = read_sphere_folder(
        folder, mask_path=Path(args.mask) if args.mask else None)
    report: dict[str, Any] = {"folder": str(folder.resolve()), "images": len(names)}
    if args.camera_info:
        if not args.radius:
            raise FingerpsCalibError(
                "--camera-info needs --radius (the sphere's radius in metres)")
        camera = load_camera_info(args.camera_info)
        if (camera.width, camera.height) != (images.shape[2], images.shape[1]):
            raise FingerpsCalibError(
                f"the images are {images.shape[2]}x{images.shape[1]} but {args.camera_info} "
                f"is for {camera.width}x{camera.height}: give this camera's intrinsics")
        distortion = camera.distortion if np.any(camera.distortion) else None
        result = calibrate_lights(
            images, camera_matrix=camera.camera_matrix, radius_m=args.radius, mask=mask,
            distortion=distortion, saturation_level=args.full_scale,
            require_whole_sphere=True)
        directions_ps = result.directions_ps
        centre = result.sphere_center_optical_m
        report.update({
            "method": "perspective (paper Sec. 3.1): sphere centre from the tangent rays, "
                      "mirror reflection at each highlight",
            "camera_info": str(Path(args.camera_info).resolve()),
            "camera_name": camera.camera_name,
            "sphere_radius_m": float(args.radius),
            "sphere_center_m": [float(x) for x in centre],
            "edge_rms_px": float(result.edge_rms_px),
        })
        highlights_raw = distort_points(result.highlights_uv, camera.camera_matrix,
                                        distortion)
        outline = sphere_outline(centre, args.radius, camera.camera_matrix, distortion)
    else:
        result = calibrate_lights_orthographic(images, mask=mask)
        directions_ps = result.directions_ps
        report.update({
            "method": "orthographic chrome sphere (no intrinsics): circle fitted to the "
                      "silhouette, view along the optical axis",
            "circle_center_uv": [float(x) for x in result.circle_center_uv],
            "circle_radius_px": float(result.circle_radius_px),
            "edge_rms_px": float(result.edge_rms_px),
        })
        highlights_raw = result.highlights_uv
        outline = circle_outline(result.circle_center_uv, result.circle_radius_px) \
            if np.isfinite(result.circle_radius_px) else None
    report["mask"] = mask is not None
    report["ok"] = bool(result.ok)
    report["problems"] = list(result.problems)
    report["leds"] = [{
        "file": name,
        "direction_ps": [float(x) for x in directions_ps[k]],
        "highlight_uv": [float(x) for x in result.highlights_uv[k]],
        "highlight_residual_px": float(result.residuals_px[k]),
    } for k, name in enumerate(names)]
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / REPORT_FILE, yaml.safe_dump(report, sort_keys=False,
                                                   default_flow_style=None,
                                                   width=100).encode("utf-8"))
    finite = result.residuals_px[np.isfinite(result.residuals_px)]
    worst = float(finite.max()) if finite.size else float("nan")
    lines = [f"{folder}: {len(names)} images, {report['method'].split(':')[0]}",
             f"edge rms {report['edge_rms_px']:.2f} px, highlight residual max {worst:.2f} px"]
    picture = lights_picture(
        images, highlights_uv=highlights_raw, directions_optical=ps_to_optical(directions_ps),
        edge_points_uv=result.edge_points_uv, outline_uv=outline,
        title="light calibration" + ("" if result.ok else " FAILED"), lines=lines,
        problems=result.problems)
    write_png(out / PICTURE_FILE, picture)
    for k, name in enumerate(names):
        d = directions_ps[k]
        print(f"  {k:2d} {name:<24} {d[0]: .4f} {d[1]: .4f} {d[2]: .4f}  "
              f"residual {result.residuals_px[k]:.2f} px")
    print(f"  {lines[1]}")
    if not result.ok:
        print("light calibration FAILED its checks (light_directions.txt not written):",
              file=sys.stderr)
        for problem in result.problems:
            print(f"  - {problem}", file=sys.stderr)
        print(f"report: {out / REPORT_FILE}, picture: {out / PICTURE_FILE}", file=sys.stderr)
        return EXIT_FAILED
    text = "".join(f"{d[0]:.8f} {d[1]:.8f} {d[2]:.8f}\n" for d in directions_ps)
    write_atomic(out / DIRECTIONS_FILE, text.encode("utf-8"))
    print(f"wrote {out / DIRECTIONS_FILE}, {out / REPORT_FILE}, {out / PICTURE_FILE}")
    return 0


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    p = argparse.ArgumentParser(
        prog="calibrate_lights",
        description="Light directions (DiLiGenT light_directions.txt) from a folder of "
                    "shiny-sphere images, one per LED, listed in filenames.txt.")
    p.add_argument("folder", help="folder with filenames.txt, the images and optionally "
                                  "mask.png")
    p.add_argument("--radius", type=positive_number,
                   help="sphere radius in metres (with --camera-info)")
    p.add_argument("--camera-info", help="camera_info YAML of the camera; without it the "
                                         "orthographic method is used")
    p.add_argument("--mask", help="mask image of the sphere (default FOLDER/mask.png if "
                                  "present)")
    p.add_argument("--out", help="output folder (default: FOLDER)")
    p.add_argument("--force", action="store_true", help="replace an existing "
                                                        "light_directions.txt")
    p.add_argument("--full-scale", type=positive_number,
                   help="saturation level of the images (default: the file's bit depth)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_calib calibrate_lights``."""
    return TOOL.main(parser(), run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
