"""offline_tune: reconstruction settings compared over a bag's bursts or a DiLiGenT folder.

Usage::

    ros2 run fingerps_recon offline_tune SOURCE --out DIR [--model lambert,hk]
        [--w 5,7,9] [--k 1,2.5,4] [--calibration lights.yaml] [--ridge-period PX]
        [--bursts N] [--jobs 2]

SOURCE is a session bag (directory or .mcap: every ``fingerps_msgs/msg/Burst`` in it, with
the bag's last light calibration and flat field, as recon_node would use them; perspective
camera from each burst's camera_info) or a DiLiGenT-layout folder (one burst; orthographic,
pixel units, as offline_recon). A bag without a light calibration needs ``--calibration``:
calib_node's ``lights.yaml`` (or its calibration directory; its flat field is used too).

Every (model, w, k) is run on every burst: one solve per burst and model, in a process pool
(``--jobs``, 2 by default), with a progress bar on stderr. Outputs in DIR:

- ``<burst>/<model>/``: ``normals.npy`` (H, W, 3) float32, unit normals in the frame of the
  light directions (PS frame), zeros off the mask; ``depth.npy`` (H, W) float32 (metres along
  the optical axis for bags; height in pixels for folders; NaN off the mask);
  ``cloud.ply`` (optical frame)
- ``<burst>/<model>/w<w>_k<k>/``: ``normals_enhanced.npy`` and ``normal_map.png`` (Eq. 12)
- ``summary.csv`` and the same table on stdout: burst, setting, ridge visibility of the
  enhanced and of the plain normals, angular error (mean/median, deg) where ground truth
  exists, valid pixels, time
- ``contact_sheet.png``: the normal maps, one row a burst, one column a setting, labelled

Bad input: one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import csv
import math
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.offline.diligent_folder import load_diligent_folder
from fingerps_recon.offline.parameter_sweep import (
    BurstInput,
    Setting,
    SettingScore,
    settings_grid,
    sweep_burst,
)
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.full_scale import full_scale_of
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import Model, Projection, ReconstructionOptions
from fingerps_recon.surface.ply import write_ply
from fingerps_ros.command_line import CommandLineTool
from fingerps_ros.errors import FingerpsError

_PROG = "offline_tune"
TOOL = CommandLineTool(_PROG, bad_input=(FingerpsError,), failed=(OSError,))
BURST_TYPE = "fingerps_msgs/msg/Burst"
LIGHTS_TYPE = "fingerps_msgs/msg/LightCalibration"
FLAT_TYPE = "fingerps_msgs/msg/FlatField"
TILE_HEIGHT = 200
LABEL_HEIGHT = 22


@dataclass(frozen=True)
class Row:
    """One line of the summary."""

    burst: str
    setting: Setting
    score: SettingScore
    time_ms: float


# ----------------------------------------------------------------------------- inputs


def _calibration_from_file(path: Path) -> tuple[np.ndarray, np.ndarray | None,
                                                np.ndarray | None, np.ndarray | None]:
    """(directions optical, LED positions, intensities, portions) from calib's files."""
    try:
        from fingerps_calib.calibration_store import load_flat_field, load_lights
        from fingerps_calib.errors import FingerpsCalibError
    except ImportError as err:
        raise FingerpsReconError(f"--calibration needs fingerps_calib ({err}); build the "
                                 "workspace and source tools/ros_env.sh") from None
    directory = path if path.is_dir() else path.parent
    try:
        record = load_lights(directory)
        flat = load_flat_field(directory)
    except FingerpsCalibError as err:
        raise FingerpsReconError(f"--calibration {path}: {err}") from None
    if record is None:
        raise FingerpsReconError(f"--calibration {path}: no lights.yaml in {directory}")
    lights = record.lights
    positions = lights.led_positions_optical_m
    return (np.asarray(lights.directions_optical, dtype=np.float64),
            None if positions is None else np.asarray(positions, dtype=np.float64),
            None if flat is None else np.asarray(flat.relative_intensities, dtype=np.float64),
            None if flat is None else np.asarray(flat.portions, dtype=np.float32))


def bursts_from_bag(path: Path, *, calibration: Path | None,
                    limit: int | None) -> list[BurstInput]:
    """Every complete burst of a bag as a `BurstInput` (recon_node's conversion)."""
    from fingerps_recon.sessions.bag_reader import SessionBagReader
    from fingerps_ros.image_conversion import image_to_array

    reader = SessionBagReader(path, raise_on_damage=False)  # tune on what is intact
    types = reader.topics()
    lights_msg = flat_msg = None
    raw = []
    for message in reader.messages():
        if message.type_name == LIGHTS_TYPE:
            lights_msg = message
        elif message.type_name == FLAT_TYPE:
            flat_msg = message
        elif message.type_name == BURST_TYPE and (limit is None or len(raw) < limit):
            raw.append(message)
    for damaged in reader.damage:
        print(f"{_PROG}: warning: {path}: bytes {damaged.start}..{damaged.end} damaged "
              f"({damaged.reason}); tuning on the intact messages (bag_recover repairs it)",
              file=sys.stderr)
    if not raw:
        raise FingerpsReconError(f"{path} holds no {BURST_TYPE} messages (topics: "
                                 f"{', '.join(types) or 'none'})")
    portions = intensities = positions = None
    if calibration is not None:
        directions, positions, intensities, portions = _calibration_from_file(calibration)
    elif lights_msg is None:
        raise FingerpsReconError(
            f"{path} holds no light calibration ({LIGHTS_TYPE}); give one with "
            "--calibration <calibration dir>/lights.yaml (calib_node's saved calibration)")
    else:
        lights = lights_msg.deserialize()
        directions = np.array([[d.x, d.y, d.z] for d in lights.directions])
        intensities = np.asarray(lights.relative_intensities, dtype=np.float64)
        positions = np.array([[p.x, p.y, p.z] for p in lights.led_positions]) \
            if lights.led_positions else None
        if flat_msg is not None:
            portions = np.stack([image_to_array(m) for m in flat_msg.deserialize().maps]
                                ).astype(np.float32)
    count = len(directions)
    bursts = []
    for message in raw:
        burst = message.deserialize()
        frames = sorted(burst.frames, key=lambda f: f.led_index)
        if [f.led_index for f in frames] != list(range(count)):
            print(f"{_PROG}: burst {burst.burst_id} skipped: LEDs "
                  f"{[f.led_index for f in frames]}, calibration has {count}", file=sys.stderr)
            continue
        images = np.stack([image_to_array(f.image) for f in frames])
        full = full_scale_of(frames[0].image.encoding)
        bursts.append(BurstInput(
            name=f"burst_{burst.burst_id:04d}", images=images,
            lights_ps=optical_to_ps(directions),
            camera_matrix=np.asarray(burst.camera_info.k, dtype=np.float64).reshape(3, 3),
            full_scale=full,
            intensities=intensities if intensities is not None and intensities.size == count
            else None,
            portions=portions if portions is not None and portions.shape == images.shape
            else None,
            dark=image_to_array(burst.dark_frame.image) if burst.has_dark_frame else None,
            led_positions_optical=positions if positions is not None and len(positions) == count
            else None))
    return bursts


def burst_from_folder(path: Path) -> BurstInput:
    """A DiLiGenT-layout folder as one `BurstInput` (orthographic, pixel units)."""
    data = load_diligent_folder(path)
    _, height, width = data.images.shape
    camera = np.array([[1.0, 0.0, (width - 1) / 2.0], [0.0, 1.0, (height - 1) / 2.0],
                       [0.0, 0.0, 1.0]])
    options = ReconstructionOptions(
        projection=Projection.ORTHOGRAPHIC, shadow_fraction=data.shadow_level / data.full_scale,
        saturation_fraction=1.0, working_distance_m=1.0)
    return BurstInput(name=path.resolve().name, images=data.images, lights_ps=data.lights_ps,
                      camera_matrix=camera, full_scale=data.full_scale,
                      intensities=data.intensities, mask=data.mask, normal_gt=data.normal_gt,
                      base_options=options)


# ----------------------------------------------------------------------------- work


def _job(burst: BurstInput, model: Model, settings: list[Setting], out: str) -> list[Row]:
    """One burst under one model: solve, write its files, score every (w, k)."""
    rec, swept = sweep_burst(burst, model, settings)
    model_dir = Path(out) / burst.name / model.value
    model_dir.mkdir(parents=True, exist_ok=True)
    np.save(model_dir / "normals.npy", rec.normals_ps)
    np.save(model_dir / "depth.npy", rec.depth_m)
    write_ply(model_dir / "cloud.ply", rec.points_optical, intensity=rec.point_albedo)
    rows = []
    for item in swept:
        setting_dir = model_dir / f"w{item.setting.w}_k{item.setting.k:g}"
        setting_dir.mkdir(exist_ok=True)
        np.save(setting_dir / "normals_enhanced.npy", item.enhanced_ps)
        rgb = normal_map_rgb(item.enhanced_ps, mask=rec.mask)
        if not cv2.imwrite(str(setting_dir / "normal_map.png"),
                           cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{setting_dir / 'normal_map.png'}: OpenCV could not write it")
        rows.append(Row(burst.name, item.setting, item.score, item.time_ms))
    return rows


def _progress(done: int, total: int) -> None:
    width = 30
    filled = int(width * done / max(total, 1))
    print(f"\r{_PROG} [{'#' * filled}{'-' * (width - filled)}] {done}/{total} solves",
          end="\n" if done == total else "", file=sys.stderr, flush=True)


def run_sweep(bursts: list[BurstInput], settings: list[Setting], out: Path, *,
              jobs: int) -> list[Row]:
    """Run every burst under every model of ``settings`` in a pool of ``jobs`` processes."""
    models = list(dict.fromkeys(s.model for s in settings))
    work = [(b, m) for b in bursts for m in models]
    rows: list[Row] = []
    _progress(0, len(work))
    # Fresh interpreters, not forks: numba's worker threads do not survive fork() in a
    # process that has used them (the child dies), and neither do rclpy's.
    with ProcessPoolExecutor(max_workers=jobs,
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(_job, b, m, settings, str(out)) for b, m in work]
        for done, future in enumerate(as_completed(futures), start=1):
            rows.extend(future.result())
            _progress(done, len(work))
    order = {s: i for i, s in enumerate(settings)}
    names = [b.name for b in bursts]
    return sorted(rows, key=lambda r: (names.index(r.burst), order[r.setting]))


# ----------------------------------------------------------------------------- summary

COLUMNS = ("burst", "setting", "model", "w", "k", "ridge_visibility",
           "ridge_visibility_plain", "error_mean_deg", "error_median_deg", "valid_pixels",
           "time_ms")


def _values(row: Row) -> list[object]:
    s = row.score
    return [row.burst, row.setting.label, row.setting.model.value, row.setting.w,
            row.setting.k, s.ridge_visibility, s.ridge_visibility_plain, s.error_mean_deg,
            s.error_median_deg, s.valid_pixels, row.time_ms]


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.3f}"
    return str(value)


def write_summary(rows: list[Row], out: Path) -> str:
    """Write summary.csv; return the table as text."""
    with open(out / "summary.csv", "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(COLUMNS)
        for row in rows:
            writer.writerow(["" if isinstance(v, float) and math.isnan(v) else v
                             for v in _values(row)])
    shown = ("burst", "setting", "ridge_visibility", "ridge_visibility_plain",
             "error_mean_deg", "error_median_deg", "valid_pixels", "time_ms")
    index = [COLUMNS.index(c) for c in shown]
    cells = [[_cell(_values(r)[i]) for i in index] for r in rows]
    widths = [max(len(h), *(len(c[j]) for c in cells)) for j, h in enumerate(shown)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(shown, widths, strict=True))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(cell, widths, strict=True))
              for cell in cells]
    return "\n".join(lines)


def write_contact_sheet(rows: list[Row], out: Path) -> Path:
    """The normal maps side by side: a row per burst, a column per setting, labelled."""
    bursts = list(dict.fromkeys(r.burst for r in rows))
    settings = list(dict.fromkeys(r.setting for r in rows))
    by_key = {(r.burst, r.setting): r for r in rows}
    tiles = []
    for burst in bursts:
        line = []
        for setting in settings:
            row = by_key.get((burst, setting))
            path = (out / burst / setting.model.value / f"w{setting.w}_k{setting.k:g}" /
                    "normal_map.png")
            image = cv2.imread(str(path)) if row is not None else None
            if image is None:
                image = np.zeros((TILE_HEIGHT, TILE_HEIGHT, 3), np.uint8)
            scale = TILE_HEIGHT / image.shape[0]
            image = cv2.resize(image, (max(1, round(image.shape[1] * scale)), TILE_HEIGHT),
                               interpolation=cv2.INTER_AREA)
            label = np.full((LABEL_HEIGHT * 2, image.shape[1], 3), 255, np.uint8)
            text2 = ""
            if row is not None:
                text2 = f"rv {_cell(row.score.ridge_visibility)}"
                if not math.isnan(row.score.error_mean_deg):
                    text2 += f" err {row.score.error_mean_deg:.2f}d"
            for i, text in enumerate((f"{burst} {setting.label}", text2)):
                cv2.putText(label, text, (4, LABEL_HEIGHT * (i + 1) - 6),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
            line.append(np.vstack([label, image]))
        height = max(t.shape[0] for t in line)
        tiles.append(np.hstack([np.pad(t, ((0, height - t.shape[0]), (0, 4), (0, 0)),
                                       constant_values=255) for t in line]))
    width = max(t.shape[1] for t in tiles)
    sheet = np.vstack([np.pad(t, ((0, 4), (0, width - t.shape[1]), (0, 0)),
                              constant_values=255) for t in tiles])
    path = out / "contact_sheet.png"
    if not cv2.imwrite(str(path), sheet):
        raise OSError(f"{path}: OpenCV could not write it")
    return path


# ----------------------------------------------------------------------------- CLI


def _list(kind: type):
    def parse(text: str) -> list:
        try:
            values = [kind(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a comma-separated list: {text!r}") from None
        if not values:
            raise argparse.ArgumentTypeError("give at least one value")
        return values
    return parse


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=_PROG, description="Compare reconstruction settings over a bag's bursts or a "
                                "DiLiGenT-layout folder.")
    parser.add_argument("source", type=Path, help="session bag (directory or .mcap) or "
                                                  "DiLiGenT-layout folder")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--model", type=_list(Model), default=[Model.LAMBERT],
                        help="comma-separated: lambert,hk (default lambert)")
    parser.add_argument("--w", type=_list(int), default=[7], help="odd patch sizes (7)")
    parser.add_argument("--k", type=_list(float), default=[2.5], help="gains (2.5)")
    parser.add_argument("--calibration", type=Path, default=None,
                        help="calib_node's lights.yaml (or its directory), for a bag without "
                             "calibration or to override the bag's")
    parser.add_argument("--ridge-period", type=float, default=None,
                        help="ridge period in pixels for the ridge visibility (default: "
                             "estimated from each map)")
    parser.add_argument("--bursts", type=int, default=None, help="at most this many bursts")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (2)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Read the source, sweep the settings, write and print the summary; return 0."""
    settings = settings_grid(args.model, args.w, args.k)
    source = args.source
    if (source / "filenames.txt").is_file():
        if args.calibration is not None:
            raise FingerpsReconError("--calibration is for bags; a folder has its lights")
        bursts = [burst_from_folder(source)]
    elif source.exists():
        bursts = bursts_from_bag(source, calibration=args.calibration, limit=args.bursts)
    else:
        raise FingerpsReconError(f"{source} does not exist")
    if not bursts:
        raise FingerpsReconError(f"no burst of {source} fits its calibration")
    if args.ridge_period is not None:
        if not args.ridge_period > 2:
            raise FingerpsReconError("--ridge-period must be more than 2 pixels")
        bursts = [replace(b, ridge_period_px=args.ridge_period) for b in bursts]
    if args.out.exists() and not args.out.is_dir():
        raise FingerpsReconError(f"--out {args.out} exists and is not a folder")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run_sweep(bursts, settings, args.out, jobs=max(1, min(args.jobs,
                                                                 os.cpu_count() or 1)))
    table = write_summary(rows, args.out)
    sheet = write_contact_sheet(rows, args.out)
    print(table)
    print(f"\n{len(bursts)} burst(s) x {len(settings)} setting(s); "
          f"{args.out / 'summary.csv'}, {sheet}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon offline_tune``; returns the exit code."""
    return TOOL.main(_parser(), run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
