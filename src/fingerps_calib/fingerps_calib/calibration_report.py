"""What the operator reads about a light calibration: its summary line and its picture.

The summary is the answer of a successful calibrate_lights call (and calib_node's log
line); the picture (``calibration_picture.lights_picture``) shows the sphere, the
highlights and the directions, with the summary and one line per LED under it.
"""

from __future__ import annotations

import numpy as np

from fingerps_calib.calibration_camera import CalibrationCamera
from fingerps_calib.calibration_picture import distort_points, lights_picture, sphere_outline
from fingerps_calib.calibration_store import LightsRecord
from fingerps_calib.lights.sphere_calibration import LightCalibrationResult


def lights_summary(record: LightsRecord) -> str:
    """One line: LEDs, placements, sphere centre, fit residuals (and the triangulation)."""
    lights = record.lights
    centre = 1e3 * lights.sphere_center_optical_m
    text = (f"{lights.led_count} LEDs calibrated from {len(lights.placements)} sphere "
            f"placement(s); sphere centre ({centre[0]:.2f}, {centre[1]:.2f}, {centre[2]:.2f}) "
            f"mm, edge rms {lights.edge_rms_px:.2f} px, highlight residual max "
            f"{np.nanmax(lights.residuals_px):.2f} px")
    tri = lights.triangulation
    if tri is not None:
        ref = 1e3 * tri.reference_point_optical_m
        text += (f"; LED positions triangulated (residual max "
                 f"{1e3 * np.nanmax(tri.position_residuals_m):.2f} mm, rays "
                 f"{np.nanmin(tri.ray_angles_deg):.1f}-{np.nanmax(tri.ray_angles_deg):.1f} deg "
                 f"apart), directions from ({ref[0]:.1f}, {ref[1]:.1f}, {ref[2]:.1f}) mm")
    return text


def lights_lines(record: LightsRecord) -> list[str]:
    """Text under the light calibration's picture: camera and date, summary, one per LED."""
    lights = record.lights
    lines = [f"camera {record.camera_name}, {record.date}", lights_summary(record)]
    tri = lights.triangulation
    for k, d in enumerate(lights.directions_optical):
        polar = np.degrees(np.arccos(np.clip(-d[2], -1, 1)))
        azimuth = np.degrees(np.arctan2(-d[1], d[0]))
        line = (f"LED {k}: {polar:.1f} deg from the view axis, azimuth {azimuth:.0f} deg, "
                f"highlight residual {lights.residuals_px[k]:.2f} px")
        if tri is not None:
            q = 1e3 * tri.led_positions_optical_m[k]
            line += (f", at ({q[0]:.1f}, {q[1]:.1f}, {q[2]:.1f}) mm +- "
                     f"{1e3 * tri.position_residuals_m[k]:.2f} mm")
        lines.append(line)
    return lines


def light_calibration_picture(
        images: np.ndarray, result: LightCalibrationResult, camera: CalibrationCamera,
        directions: np.ndarray, placement_directions: list[np.ndarray], *, title: str,
        lines: list[str], problems: tuple[str, ...] = ()) -> np.ndarray:
    """The operator's picture of a light calibration, in the raw image's pixels.

    Parameters
    ----------
    images : (K, H, W)
        The sphere images the calibration was made from.
    result : LightCalibrationResult
        This placement's fit (highlights, silhouette).
    camera : CalibrationCamera
        The intrinsics used (the highlights and the outline are distorted back with them).
    directions : (K, 3) float64
        The directions to draw, optical frame.
    placement_directions : list of (K, 3) float64
        Each placement's directions when several were combined, else empty.
    title, lines, problems
        Text of the picture.

    Returns
    -------
    (h, w, 3) uint8
        BGR picture.
    """
    return lights_picture(
        images,
        highlights_uv=distort_points(result.highlights_uv, camera.matrix, camera.distortion),
        directions_optical=directions, edge_points_uv=result.edge_points_uv,
        outline_uv=sphere_outline(result.sphere_center_optical_m, result.radius_m,
                                  camera.matrix, camera.distortion),
        placement_directions=placement_directions, title=title, lines=lines,
        problems=problems)
