"""Pictures an operator looks at to see whether a calibration worked (PNG, OpenCV drawing).

`lights_picture`: left, the sphere (the pixel-wise maximum of its images, brightened) with
the silhouette points found (yellow), the fitted sphere's outline (green) and each LED's
highlight (a numbered cross); right, the light directions as a polar plot seen from the
camera (PS frame: x right, y up; the radius is the angle from the viewing direction, rings
every 15 deg); with two or more placements each placement's own mirror directions are small
circles around the combined direction; below, the figures (sphere centre, residuals, LED
positions) and, for a refused calibration, the problems in red.

`flat_field_picture`: one heat map per LED (viridis: p_k from the lowest value of all maps,
rounded down to 0.1, in dark blue, to 1 in yellow), with the LED's relative intensity and
fit residual, and a colour bar.

Pictures are (H, W, 3) uint8 BGR arrays; `write_png` saves one atomically.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from fingerps_calib.calibration_store import write_atomic
from fingerps_calib.errors import FingerpsCalibError
from fingerps_recon.photometric.frames import optical_to_ps

_PANEL = 480
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_WHITE, _GREEN, _YELLOW, _RED, _GREY = (255, 255, 255), (80, 220, 80), (0, 220, 255), \
    (60, 60, 255), (150, 150, 150)
_POLAR_MAX_DEG = 60.0


def led_colour(k: int) -> tuple[int, int, int]:
    """A distinct BGR colour for LED ``k`` (hues around the circle)."""
    hsv = np.uint8([[[int(180 * ((k * 0.381966) % 1.0)), 200, 255]]])
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def lights_picture(
    images: np.ndarray,
    *,
    highlights_uv: np.ndarray,
    directions_optical: np.ndarray,
    edge_points_uv: np.ndarray | None = None,
    outline_uv: np.ndarray | None = None,
    placement_directions: Sequence[np.ndarray] = (),
    title: str = "light calibration",
    lines: Sequence[str] = (),
    problems: Sequence[str] = (),
) -> np.ndarray:
    """The picture of one light calibration (see the module docstring).

    Parameters
    ----------
    images : (K, H, W) or (H, W) array
        The sphere images (of the latest placement).
    highlights_uv : (K, 2) float
        Highlight centroids in the images' (raw) pixel coordinates; NaN rows are skipped.
    directions_optical : (K, 3) float
        The directions to plot (the calibration in force), optical frame; NaN rows skipped.
    edge_points_uv : (N, 2) float, optional
        Silhouette points found.
    outline_uv : (M, 2) float, optional
        The fitted sphere's outline (`sphere_outline`, or a circle).
    placement_directions : sequence of (K, 3) float
        Each placement's own directions (drawn as small circles), optical frame.
    title : str
    lines : sequence of str
        Text printed under the panels.
    problems : sequence of str
        Printed in red (a refused calibration).

    Returns
    -------
    (H, W, 3) uint8 BGR
    """
    stack = np.asarray(images, dtype=np.float64)
    if stack.ndim == 2:
        stack = stack[None]
    sphere = _sphere_panel(stack.max(axis=0), highlights_uv, edge_points_uv, outline_uv)
    polar = _polar_panel(np.asarray(directions_optical, dtype=np.float64),
                         placement_directions)
    width = 2 * _PANEL
    rows = _text_block([title, *lines], width, colour=_WHITE)
    if problems:
        rows = np.vstack([rows, _text_block([f"- {p}" for p in problems], width,
                                            colour=_RED)])
    return np.vstack([np.hstack([sphere, polar]), rows])


def sphere_outline(center_optical_m: np.ndarray, radius_m: float, camera_matrix: np.ndarray,
                   distortion: np.ndarray | None = None, *, points: int = 360) -> np.ndarray:
    """(points, 2) raw pixel coordinates of a sphere's silhouette (its tangent cone).

    Returns an empty (0, 2) array when the centre is not finite or not in front of the
    camera by more than the radius.
    """
    center = np.asarray(center_optical_m, dtype=np.float64)
    if not (np.all(np.isfinite(center)) and center[2] > radius_m > 0):
        return np.zeros((0, 2))
    axis = center / np.linalg.norm(center)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    alpha = np.arcsin(min(radius_m / np.linalg.norm(center), 1.0))
    t = np.linspace(0, 2 * np.pi, points, endpoint=False)[:, None]
    rays = np.cos(alpha) * axis + np.sin(alpha) * (np.cos(t) * e1 + np.sin(t) * e2)
    coeffs = np.zeros(5) if distortion is None else np.asarray(distortion, float).ravel()
    uv, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                              np.asarray(camera_matrix, float), coeffs)
    return uv.reshape(-1, 2)


def circle_outline(center_uv: np.ndarray, radius_px: float, *, points: int = 360
                   ) -> np.ndarray:
    """(points, 2) pixel coordinates of a circle."""
    t = np.linspace(0, 2 * np.pi, points, endpoint=False)
    return np.asarray(center_uv, float)[None, :] + radius_px * np.column_stack(
        [np.cos(t), np.sin(t)])


def distort_points(uv: np.ndarray, camera_matrix: np.ndarray,
                   distortion: np.ndarray | None) -> np.ndarray:
    """Ideal pixel coordinates (N, 2) -> raw (distorted) ones; NaN rows stay NaN."""
    uv = np.asarray(uv, dtype=np.float64)
    if distortion is None:
        return uv.copy()
    k = np.asarray(camera_matrix, dtype=np.float64)
    out = np.full_like(uv, np.nan)
    good = np.all(np.isfinite(uv), axis=1)
    if good.any():
        rays = np.column_stack([uv[good], np.ones(good.sum())]) @ np.linalg.inv(k).T
        projected, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k,
                                         np.asarray(distortion, float).ravel())
        out[good] = projected.reshape(-1, 2)
    return out


def flat_field_picture(
    portions: np.ndarray,
    *,
    relative_intensities: np.ndarray,
    fit_residuals: np.ndarray | None = None,
    title: str = "flat field",
    lines: Sequence[str] = (),
) -> np.ndarray:
    """Heat maps of the flat-field maps p_k (see the module docstring).

    Parameters
    ----------
    portions : (K, H, W) float
        Maps in (0, 1].
    relative_intensities : (K,) float
    fit_residuals : (K,) float, optional
        Fractions (shown in percent).
    title : str
    lines : sequence of str

    Returns
    -------
    (H, W, 3) uint8 BGR
    """
    maps = np.asarray(portions, dtype=np.float64)
    if maps.ndim != 3:
        raise FingerpsCalibError(f"portions has shape {maps.shape}, expected (K, H, W)")
    n_led, h, w = maps.shape
    cols = min(4, n_led)
    tile_w = 240
    tile_h = max(1, round(tile_w * h / w))
    # Colours from the lowest value of all maps (rounded down to 0.1) to 1.
    low = float(np.floor(10 * np.clip(np.nanmin(maps), 0, 0.9)) / 10)
    tiles = []
    for k in range(n_led):
        scaled = cv2.resize((np.clip(maps[k], low, 1) - low) / (1 - low), (tile_w, tile_h),
                            interpolation=cv2.INTER_AREA)
        tile = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
        label = f"LED {k}  I={relative_intensities[k]:.2f}"
        if fit_residuals is not None:
            label += f"  fit {100 * fit_residuals[k]:.1f}%"
        caption = np.zeros((22, tile_w, 3), np.uint8)
        cv2.putText(caption, label, (4, 16), _FONT, 0.42, _WHITE, 1, cv2.LINE_AA)
        tiles.append(np.vstack([caption, tile]))
    blank = np.zeros_like(tiles[0])
    while len(tiles) % cols:
        tiles.append(blank)
    grid = np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])
    bar = cv2.applyColorMap(np.linspace(255, 0, grid.shape[0]).astype(np.uint8)[:, None]
                            .repeat(20, axis=1), cv2.COLORMAP_VIRIDIS)
    legend = np.zeros((grid.shape[0], 44, 3), np.uint8)
    cv2.putText(legend, "1", (4, 14), _FONT, 0.42, _WHITE, 1, cv2.LINE_AA)
    cv2.putText(legend, f"{low:.1f}", (4, grid.shape[0] - 4), _FONT, 0.42, _WHITE, 1,
                cv2.LINE_AA)
    body = np.hstack([grid, bar, legend])
    return np.vstack([body, _text_block([title, *lines], body.shape[1], colour=_WHITE)])


def write_png(path: str | os.PathLike[str], picture: np.ndarray) -> Path:
    """Save a picture as PNG (atomically); return the path.

    Raises
    ------
    FingerpsCalibError
        Encoding or writing failed.
    """
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise FingerpsCalibError(f"cannot encode the picture {picture.shape} as PNG")
    path = Path(path)
    write_atomic(path, encoded.tobytes())
    return path


# ------------------------------------------------------------------------------ private


def _sphere_panel(image: np.ndarray, highlights_uv: np.ndarray,
                  edge_points_uv: np.ndarray | None, outline_uv: np.ndarray | None
                  ) -> np.ndarray:
    """The sphere, cropped around its outline and scaled to the panel, with overlays."""
    h, w = image.shape
    edges = np.zeros((0, 2)) if edge_points_uv is None else np.asarray(edge_points_uv, float)
    outline = np.zeros((0, 2)) if outline_uv is None else np.asarray(outline_uv, float)
    around = outline if len(outline) >= 5 else edges
    if len(around) >= 5:
        centre = around.mean(axis=0)
        half = 1.25 * float(np.max(np.linalg.norm(around - centre, axis=1)))
    else:
        centre, half = np.array([w / 2, h / 2]), max(w, h) / 2
    scale = _PANEL / (2 * half)
    offset = centre - half  # image point shown at the panel's top-left corner
    warp = np.array([[scale, 0.0, -scale * offset[0]], [0.0, scale, -scale * offset[1]]])
    # Brighten: the diffuse sphere is dim next to its highlights (a gamma of 0.4).
    top = float(np.percentile(image, 99.9)) or 1.0
    shown = (255 * np.clip(image / top, 0, 1) ** 0.4).astype(np.uint8)
    panel = cv2.warpAffine(shown, warp, (_PANEL, _PANEL), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=40)
    panel = cv2.cvtColor(panel, cv2.COLOR_GRAY2BGR)

    def to_panel(uv: np.ndarray) -> np.ndarray:
        return (uv - offset) * scale

    for u, v in to_panel(edges[:: max(1, len(edges) // 240)]):
        cv2.circle(panel, (round(u), round(v)), 1, _YELLOW, -1, cv2.LINE_AA)
    if len(outline) >= 3:
        cv2.polylines(panel, [np.round(to_panel(outline)).astype(np.int32)], True, _GREEN, 1,
                      cv2.LINE_AA)
    for index, (u, v) in enumerate(to_panel(np.asarray(highlights_uv, dtype=np.float64))):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        colour = led_colour(index)
        cv2.drawMarker(panel, (round(u), round(v)), colour, cv2.MARKER_CROSS, 14, 1,
                       cv2.LINE_AA)
        cv2.putText(panel, str(index), (round(u) + 6, round(v) - 6), _FONT, 0.5, colour, 1,
                    cv2.LINE_AA)
    cv2.putText(panel, "sphere: silhouette (yellow), fit (green), highlights", (8, 18),
                _FONT, 0.45, _WHITE, 1, cv2.LINE_AA)
    return panel


def _polar_panel(directions_optical: np.ndarray,
                 per_placement: Sequence[np.ndarray]) -> np.ndarray:
    """Directions as seen from the camera: PS x right, y up; radius = angle from the view."""
    panel = np.full((_PANEL, _PANEL, 3), 25, np.uint8)
    c = _PANEL / 2
    radius = 0.45 * _PANEL
    for ring in range(15, int(_POLAR_MAX_DEG) + 1, 15):
        r = radius * ring / _POLAR_MAX_DEG
        cv2.circle(panel, (round(c), round(c)), round(r), _GREY, 1, cv2.LINE_AA)
        cv2.putText(panel, f"{ring}", (round(c + r * 0.71) + 2, round(c - r * 0.71) - 2),
                    _FONT, 0.4, _GREY, 1, cv2.LINE_AA)
    cv2.line(panel, (round(c - radius), round(c)), (round(c + radius), round(c)), _GREY, 1)
    cv2.line(panel, (round(c), round(c - radius)), (round(c), round(c + radius)), _GREY, 1)

    def point(direction_optical: np.ndarray) -> tuple[int, int] | None:
        d = optical_to_ps(np.asarray(direction_optical, dtype=np.float64))
        if not np.all(np.isfinite(d)):
            return None
        polar = np.degrees(np.arccos(np.clip(d[2], -1.0, 1.0)))
        azimuth = np.arctan2(d[1], d[0])
        r = radius * min(polar, _POLAR_MAX_DEG) / _POLAR_MAX_DEG
        return round(c + r * np.cos(azimuth)), round(c - r * np.sin(azimuth))

    for directions in per_placement:
        for k, d in enumerate(directions):
            p = point(d)
            if p is not None:
                cv2.circle(panel, p, 4, led_colour(k), 1, cv2.LINE_AA)
    for k, d in enumerate(directions_optical):
        p = point(d)
        if p is None:
            continue
        cv2.circle(panel, p, 5, led_colour(k), -1, cv2.LINE_AA)
        cv2.putText(panel, str(k), (p[0] + 7, p[1] - 7), _FONT, 0.5, led_colour(k), 1,
                    cv2.LINE_AA)
    cv2.putText(panel, "directions seen from the camera (x right, y up)", (8, 18), _FONT,
                0.45, _WHITE, 1, cv2.LINE_AA)
    cv2.putText(panel, "rings: degrees from the view axis", (8, _PANEL - 10), _FONT, 0.42,
                _GREY, 1, cv2.LINE_AA)
    return panel


def _text_block(lines: Sequence[str], width: int, *, colour: tuple[int, int, int]
                ) -> np.ndarray:
    """Lines of text, wrapped to ``width`` pixels, white or coloured on black."""
    wrapped: list[str] = []
    chars = max(20, int(width / 8.2))
    for line in lines:
        words, current = line.split(" "), ""
        for word in words:
            if current and len(current) + 1 + len(word) > chars:
                wrapped.append(current)
                current = "  " + word
            else:
                current = f"{current} {word}" if current else word
        wrapped.append(current)
    block = np.zeros((20 * len(wrapped) + 10, width, 3), np.uint8)
    for i, line in enumerate(wrapped):
        cv2.putText(block, line, (8, 20 * i + 20), _FONT, 0.45, colour, 1, cv2.LINE_AA)
    return block
