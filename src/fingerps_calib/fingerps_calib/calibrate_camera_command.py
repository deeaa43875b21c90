"""``calibrate_camera``: camera intrinsics from a folder of checkerboard images.

Every PNG, JPEG, BMP or TIFF image in the folder is a view of a flat checkerboard with
``--pattern`` inner corners (columns x rows, e.g. 9x6 for a board of 10 x 7 squares) of
side ``--square`` metres. Writes the intrinsics as a camera_info YAML (the format
camera_calibration writes and camera_info_manager reads; calib_node's
``camera_info_file``, calibrate_lights' ``--camera-info``) to ``--out`` (default
FOLDER/camera_info.yaml) or where ``--camera-info-url`` points (driver_node's
``camera_info_url``: the same resolution, the same atomic owner-only write as its
``set_camera_info``), and prints the reprojection error per image.

Exit status: 0 calibrated, 1 the calibration failed (too few boards found, reprojection
error too large), 2 bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_url import (
    check_camera_name,
    resolve_camera_info_url,
    store_camera_info,
)
from fingerps_calib.intrinsics.checkerboard_calibration import calibrate_checkerboard
from fingerps_ros.command_line import EXIT_FAILED, CommandLineTool, positive_number

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
TOOL = CommandLineTool("calibrate_camera", bad_input=(FingerpsCalibError,))


def _pattern(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give the inner corners as COLSxROWS, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise argparse.ArgumentTypeError(f"{text}: at least 2x2 inner corners")
    return cols, rows


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    p = argparse.ArgumentParser(
        prog="calibrate_camera",
        description="Camera intrinsics (camera_info YAML) from checkerboard images.")
    p.add_argument("folder", help="folder of checkerboard images")
    p.add_argument("--pattern", type=_pattern, required=True,
                   help="inner corners COLSxROWS, e.g. 9x6 for 10 x 7 squares")
    p.add_argument("--square", type=positive_number, required=True, help="square side, metres")
    p.add_argument("--camera-name", default="camera", help="name written into the file")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--out", help="output file (default FOLDER/camera_info.yaml)")
    where.add_argument(
        "--camera-info-url", metavar="URL",
        help="write where driver_node's camera_info_url looks (camera_info_manager's rules: "
             "file:///..., package://..., ${NAME}, ${ROS_HOME}); '' = "
             "~/.ros/camera_info/<camera-name>.yaml, the driver's default")
    p.add_argument("--max-rms", type=positive_number, default=1.0,
                   help="largest acceptable rms reprojection error, pixels (default 1)")
    return p


def run(args: argparse.Namespace) -> int:
    """Calibrate and write the file; return the exit status."""
    folder = Path(args.folder)
    if args.camera_info_url is not None:
        out = resolve_camera_info_url(args.camera_info_url,
                                      check_camera_name(args.camera_name))
    else:
        out = Path(args.out) if args.out else folder / "camera_info.yaml"
    if not folder.is_dir():
        raise FingerpsCalibError(f"{folder} is not a folder of checkerboard images")
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FingerpsCalibError(
            f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}; take 10-20 views of the "
            "board")
    images = []
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FingerpsCalibError(f"cannot read image {path}")
        images.append(image)
    try:
        result = calibrate_checkerboard(images, pattern=args.pattern, square_m=args.square,
                                        camera_name=args.camera_name,
                                        max_rms_px=args.max_rms)
    except FingerpsCalibError as exc:
        print(f"calibrate_camera: calibration failed: {exc}", file=sys.stderr)
        for index, path in enumerate(files):
            print(f"  {index:3d} {path.name}", file=sys.stderr)
        return EXIT_FAILED
    store_camera_info(out, result.intrinsics)
    for path, found, rms in zip(files, result.found, result.view_rms_px, strict=True):
        state = f"{rms:.3f} px" if found else "board not found"
        print(f"  {path.name:<32} {state}")
    k = result.intrinsics.camera_matrix
    print(f"board found in {int(result.found.sum())} of {len(files)} images; rms "
          f"reprojection error {result.rms_px:.3f} px")
    print(f"fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}; "
          f"distortion {np.round(result.intrinsics.distortion, 5).tolist()}")
    print(f"wrote {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_calib calibrate_camera``."""
    return TOOL.main(parser(), run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
