"""The README's pictures of the viewer configs: docs/viewing/foxglove_layout.png, fingerps_rviz.png.

Neither Foxglove nor RViz runs on the build machine (no GPU, no package source for them), so
these are not screenshots. They are renderings of the topics the configs name, laid out as
the configs arrange them:

- the data: one burst of the simulated rig (a synthetic fingerprint:
  ``RigConfig(finger=FingertipShape(identity=IDENTITY))``), calibrated with the rig's true
  LED positions and its white-target flat field (as ``bench/bench_fingerprint.py`` does),
  reconstructed with recon_node's defaults (HK, ridge enhancement w 7, k 2.5), the print
  made by ``rolled_print`` as recon_node does with ``fingerprint:=true``. What each topic
  would carry: ``normal_map`` (its PNG companion is lossless, so the same pixels),
  ``fingerprint``, ``depth``, ``points`` (x y z, intensity = albedo), ``image_raw`` (the
  burst's last LED, the image a viewer shows last);
- the layout: src/fingerps_recon/config/foxglove_layout.json's ``layout`` tree (split
  directions and percentages) and panel configs; fingerps.rviz's displays (image panes in
  the left dock, where RViz puts them when no window state is saved; the Displays and Views
  panels; the enabled point cloud display in the 3D view);
- the 3D views: each config's own camera (Foxglove ``cameraState``: distance, phi,
  thetaOffset, targetOffset, fovy, as its 3D panel places the camera; RViz's Orbit view:
  distance, focal point, pitch, yaw, field of view, z as the up axis), points coloured as the
  config says (Foxglove ``colorField``/``colorMap`` turbo over the cloud's min..max; RViz's
  Intensity transformer with its rainbow, autocomputed bounds); the 32FC1 depth in RViz's
  Image display normalised to its min..max, as RViz does;
- the diagnostics list: the status names the graph's nodes publish on /diagnostics, with
  the message each gives while healthy (driver_node with the simulated board, calib_node,
  recon_node, recorder_node).

Run (after ``source tools/ros_env.sh``): ``python tools/render_viewing_pictures.py``
[``--out docs/viewing``]; ~10 s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from fingerps_calib.flat_field_calibration import flat_field_maps
from fingerps_driver.board.board_emulator import FIRMWARE
from fingerps_driver.simulation import FingertipShape, RigConfig, Scene, SimulatedRig
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import (
    Model,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.surface.rolled_print import rolled_print
from fingerps_ros.privacy import start_private_tool

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "src" / "fingerps_recon" / "config"
IDENTITY = 3
SEED = 14
SIZE = (1280, 760)  # width, height of each picture

# (level, status name, message while healthy) as the nodes publish them
DIAGNOSTICS = (
    (0, "driver: board", f"connected ({FIRMWARE})"),
    (0, "driver: camera", "ok"),
    (0, "driver: bursts", "ok"),
    (0, "calib: calibration", "ok"),
    (0, "recon: reconstruction", "ok"),
    (0, "recorder: recording", "ok"),
)
FONT = cv2.FONT_HERSHEY_SIMPLEX
TEXT = (225, 222, 220)  # BGR
MUTED = (150, 146, 140)


@dataclass(frozen=True)
class Capture:
    """What the topics carry for one burst (module docstring)."""

    normal_map: np.ndarray   # (H, W, 3) uint8 RGB
    fingerprint: np.ndarray  # (h, w) uint8
    depth_m: np.ndarray      # (H, W) float32, NaN off the finger
    points: np.ndarray       # (N, 3) float32, optical frame, metres
    albedo: np.ndarray       # (N,) float32, the cloud's intensity field
    raw: np.ndarray          # (H, W) uint8, the last LED's image


def capture() -> Capture:
    """One burst of the simulated rig through recon_node's pipeline and the print."""
    rig = SimulatedRig(RigConfig(finger=FingertipShape(identity=IDENTITY)))
    leds = range(rig.led_count)
    white = np.stack([rig.render(Scene.WHITE_TARGET, [k], rng=np.random.default_rng(SEED + k))
                      for k in leds])
    dark = rig.render(Scene.WHITE_TARGET, [], rng=np.random.default_rng(SEED - 1))
    flat = flat_field_maps(white, dark=dark)
    options = ReconstructionOptions(model=Model.HK, enhance=True)
    prepared = prepare_calibration(
        rig.light_directions_ps(), camera_matrix=rig.camera_matrix, shape=white.shape[1:],
        intensities=flat.relative_intensities, portions=flat.portions,
        led_positions_optical=rig.led_positions_optical, options=options)
    images = np.stack([rig.render(Scene.FINGER, [k], rng=np.random.default_rng(SEED + 100 + k))
                       for k in leds])
    result = reconstruct_prepared(images, prepared, full_scale=rig.max_value(), options=options)
    shown = result.enhanced_ps if result.enhanced_ps is not None else result.normals_ps
    fingerprint = rolled_print(result.depth_m, mask=result.mask,
                               camera_matrix=rig.camera_matrix, normals_ps=result.normals_ps)
    return Capture(normal_map_rgb(shown, mask=result.mask), fingerprint.image, result.depth_m,
                   result.points_optical, result.point_albedo, images[-1])


# --- drawing -------------------------------------------------------------------------------

def hex_bgr(text: str) -> tuple[int, int, int]:
    r, g, b = (int(text.lstrip("#")[i:i + 2], 16) for i in (0, 2, 4))
    return b, g, r


def rviz_bgr(text: str) -> tuple[int, int, int]:
    r, g, b = (int(v) for v in text.split(";"))
    return b, g, r


def put_text(canvas: np.ndarray, text: str, x: int, y: int, *, scale: float = 0.42,
             color: tuple[int, int, int] = TEXT, width: int | None = None) -> None:
    """Text with its baseline at y, cut to fit ``width`` pixels."""
    if width is not None and cv2.getTextSize(text, FONT, scale, 1)[0][0] > width:
        while text and cv2.getTextSize(text + "...", FONT, scale, 1)[0][0] > width:
            text = text[:-1]
        text += "..."
    cv2.putText(canvas, text, (x, y), FONT, scale, color, 1, cv2.LINE_AA)


def fit_image(canvas: np.ndarray, image: np.ndarray, rect: tuple[int, int, int, int]) -> None:
    """Draw ``image`` (gray or BGR) into rect (x, y, w, h), aspect kept, centred."""
    x, y, w, h = rect
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    s = min(w / image.shape[1], h / image.shape[0])
    iw, ih = max(1, int(image.shape[1] * s)), max(1, int(image.shape[0] * s))
    small = cv2.resize(image, (iw, ih), interpolation=cv2.INTER_AREA)
    ox, oy = x + (w - iw) // 2, y + (h - ih) // 2
    canvas[oy:oy + ih, ox:ox + iw] = small


def splat(canvas: np.ndarray, rect: tuple[int, int, int, int], points: np.ndarray,
          colors: np.ndarray, camera: tuple[np.ndarray, np.ndarray], fovy_rad: float,
          size_px: int) -> None:
    """Perspective projection of points (N, 3) into rect, far to near, each a square of
    ``size_px``. ``camera`` = (position (3,), rotation (3, 3) whose columns are the camera's
    right, up and backward axes in the points' frame)."""
    x, y, w, h = rect
    position, axes = camera
    rel = (points - position) @ axes  # (right, up, backward) coordinates
    depth = -rel[:, 2]
    front = depth > 1e-6
    f = (h / 2) / math.tan(fovy_rad / 2)
    u = (w / 2 + f * rel[front, 0] / depth[front]).astype(int)
    v = (h / 2 - f * rel[front, 1] / depth[front]).astype(int)
    order = np.argsort(-depth[front])
    u, v, c = u[order], v[order], colors[front][order]
    view = canvas[y:y + h, x:x + w]
    for du in range(size_px):
        for dv in range(size_px):
            uu, vv = u + du - size_px // 2, v + dv - size_px // 2
            inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            view[vv[inside], uu[inside]] = c[inside]


def normalized(values: np.ndarray) -> np.ndarray:
    lo, hi = float(np.min(values)), float(np.max(values))
    return (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values)


def turbo(values01: np.ndarray) -> np.ndarray:
    """Google's Turbo colour map (Foxglove's ``turbo``), BGR uint8 (N, 3)."""
    index = np.clip(np.round(values01 * 255), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(index.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)


def rviz_rainbow(values01: np.ndarray, *, invert: bool) -> np.ndarray:
    """RViz's Intensity transformer with ``Use rainbow``: getRainbowColor(1 - t), BGR uint8."""
    value = np.clip(values01 if invert else 1.0 - values01, 0.0, 1.0)
    h = value * 5.0 + 1.0
    i = np.floor(h).astype(int)
    f = h - i
    f = np.where(i % 2 == 0, 1.0 - f, f)
    n = 1.0 - f
    one, zero = np.ones_like(n), np.zeros_like(n)
    r = np.select([i <= 1, i == 2, i == 3, i == 4], [n, zero, zero, n], one)
    g = np.select([i <= 1, i == 2, i == 3, i == 4], [zero, n, one, one], n)
    b = np.select([i <= 1, i == 2, i == 3, i == 4], [one, one, n, zero], zero)
    return (np.stack([b, g, r], axis=1) * 255).astype(np.uint8)


def foxglove_camera(state: dict) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """Foxglove's 3D panel camera (CameraStateSettings): position target + spherical(distance,
    phi, -thetaOffset) turned +90 deg about x; orientation Rz(theta) Rx(phi)."""
    phi, theta = math.radians(state["phi"]), -math.radians(state["thetaOffset"])
    rz = np.array([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0],
                   [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(phi), -math.sin(phi)],
                   [0, math.sin(phi), math.cos(phi)]])
    axes = rz @ rx
    position = np.asarray(state["targetOffset"], dtype=float) + state["distance"] * axes[:, 2]
    return (position, axes), math.radians(state["fovy"])


def rviz_orbit_camera(view: dict) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """RViz's Orbit view controller: the eye at focal point + distance * (cos yaw cos pitch,
    sin yaw cos pitch, sin pitch), looking at the focal point, z the fixed up axis."""
    focal = np.array([view["Focal Point"][k] for k in ("X", "Y", "Z")], dtype=float)
    yaw, pitch, d = float(view["Yaw"]), float(view["Pitch"]), float(view["Distance"])
    position = focal + d * np.array([math.cos(yaw) * math.cos(pitch),
                                     math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    forward = (focal - position) / d
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return (position, np.stack([right, up, -forward], axis=1)), float(
        view.get("Field of View", math.pi / 4))


# --- Foxglove ------------------------------------------------------------------------------

FOX_BG, FOX_PANEL, FOX_BAR, FOX_LINE = (26, 21, 21), (34, 29, 29), (48, 42, 42), (66, 60, 60)


def mosaic(node: dict | str, rect: tuple[int, int, int, int]) -> list[tuple[str, tuple]]:
    """(panel id, rect) of every leaf of a Foxglove ``layout`` tree split over rect."""
    if isinstance(node, str):
        return [(node, rect)]
    x, y, w, h = rect
    share = node.get("splitPercentage", 50.0) / 100.0
    if node["direction"] == "row":
        cut = round(w * share)
        return (mosaic(node["first"], (x, y, cut, h))
                + mosaic(node["second"], (x + cut, y, w - cut, h)))
    cut = round(h * share)
    return (mosaic(node["first"], (x, y, w, cut))
            + mosaic(node["second"], (x, y + cut, w, h - cut)))


def foxglove_picture(layout: dict, data: Capture) -> np.ndarray:
    width, height = SIZE
    canvas = np.full((height, width, 3), FOX_BG, dtype=np.uint8)
    canvas[:30] = (40, 34, 34)
    put_text(canvas, "Foxglove - layout config/foxglove_layout.json", 12, 20, scale=0.5)
    put_text(canvas, "rendering of the topics as the layout arranges them, not a screenshot",
             width - 560, 20, color=MUTED)
    images = {"/fingerps/normal_map/compressed": cv2.cvtColor(data.normal_map,
                                                              cv2.COLOR_RGB2BGR),
              "/fingerps/fingerprint/compressed": data.fingerprint,
              "/fingerps/image_raw": data.raw}
    for panel_id, (x, y, w, h) in mosaic(layout["layout"], (0, 30, width, height - 30)):
        config = layout["configById"][panel_id]
        kind = panel_id.split("!")[0]
        x, y, w, h = x + 2, y + 2, w - 4, h - 4
        canvas[y:y + h, x:x + w] = FOX_PANEL
        cv2.rectangle(canvas, (x, y), (x + w - 1, y + h - 1), FOX_LINE, 1)
        canvas[y + 1:y + 24, x + 1:x + w - 1] = FOX_BAR
        topic = config.get("imageMode", {}).get("imageTopic") or config.get("topicToRender") or (
            next(iter(config.get("topics", {})), ""))
        put_text(canvas, config.get("foxglovePanelTitle", kind), x + 8, y + 17, width=w - 16)
        content = (x + 1, y + 25, w - 2, h - 26)
        if kind == "Image":
            put_text(canvas, topic, x + 8, y + h - 8, color=MUTED, scale=0.38)
            fit_image(canvas, images[topic], (content[0], content[1], content[2],
                                              content[3] - 16))
        elif kind == "3D":
            bg = hex_bgr(config.get("scene", {}).get("backgroundColor", "#15151a"))
            cx, cy, cw, ch = content
            canvas[cy:cy + ch, cx:cx + cw] = bg
            settings = config["topics"][topic]
            field = settings["colorField"]
            values = data.albedo if field == "intensity" else data.points[:, "xyz".index(field)]
            camera, fovy = foxglove_camera(config["cameraState"])
            splat(canvas, content, data.points, turbo(normalized(values)), camera, fovy,
                  round(settings.get("pointSize", 1.5)))
            put_text(canvas, f"{topic}  colour: {field} ({settings['colorMap']})", x + 8,
                     y + h - 8, color=MUTED, scale=0.38)
            put_text(canvas, f"display frame {config['followTf']}", x + 8, y + 42,
                     color=MUTED, scale=0.38)
        elif kind == "DiagnosticSummary":
            row = y + 50
            put_text(canvas, f"{topic}   (status names as the nodes publish them)", x + 10,
                     row - 8, color=MUTED, scale=0.38)
            for level, name, message in DIAGNOSTICS:
                colour = [(89, 196, 95), (50, 190, 230), (80, 80, 230)][level]
                cv2.circle(canvas, (x + 16, row + 6), 5, colour, -1, cv2.LINE_AA)
                put_text(canvas, name, x + 28, row + 11)
                put_text(canvas, message, x + 230, row + 11, color=MUTED, width=w - 240)
                row += 26
    return canvas


# --- RViz ----------------------------------------------------------------------------------

RV_WINDOW, RV_PANEL, RV_BAR, RV_LINE, RV_TEXT = ((236, 236, 236), (250, 250, 250),
                                                 (214, 214, 214), (170, 170, 170), (30, 30, 30))


def rviz_picture(config: dict, data: Capture) -> np.ndarray:
    width, height = SIZE
    canvas = np.full((height, width, 3), RV_WINDOW, dtype=np.uint8)
    manager = config["Visualization Manager"]
    displays = manager["Displays"]
    put_text(canvas, "RViz - config/fingerps.rviz    File  Panels  Help", 10, 18,
             color=RV_TEXT, scale=0.45)
    put_text(canvas, "rendering of the topics as the config arranges them, not a screenshot",
             width - 560, 18, color=(90, 90, 90))
    tools = [tool["Class"].split("/")[-1] for tool in manager["Tools"]]
    tx = 10
    for tool in tools:
        tw = cv2.getTextSize(tool, FONT, 0.42, 1)[0][0] + 16
        cv2.rectangle(canvas, (tx, 27), (tx + tw, 49), RV_LINE, 1)
        put_text(canvas, tool, tx + 8, 43, color=RV_TEXT)
        tx += tw + 6
    top, left_w, right_w = 56, 300, 230

    def pane(title: str, rect: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        x, y, w, h = rect
        canvas[y:y + h, x:x + w] = RV_PANEL
        cv2.rectangle(canvas, (x, y), (x + w - 1, y + h - 1), RV_LINE, 1)
        canvas[y + 1:y + 21, x + 1:x + w - 1] = RV_BAR
        put_text(canvas, title, x + 8, y + 15, color=RV_TEXT, width=w - 16)
        return x + 1, y + 22, w - 2, h - 23

    # left dock: the Displays panel, then the enabled Image displays' panes
    tree_h = 26 + 20 * (len(displays) + 2)
    x, y, w, _ = pane("Displays", (4, top, left_w, tree_h))
    rows = [("Global Options", None, ""),
            ("Global Status: Ok", None, ""),
            *((d["Name"], d["Enabled"], d["Topic"]["Value"]) for d in displays)]
    for i, (name, enabled, topic) in enumerate(rows):
        ry = y + 16 + 20 * i
        if enabled is not None:
            cv2.rectangle(canvas, (x + 8, ry - 10), (x + 18, ry), RV_TEXT, 1)
            if enabled:
                cv2.line(canvas, (x + 9, ry - 5), (x + 12, ry - 1), RV_TEXT, 2, cv2.LINE_AA)
                cv2.line(canvas, (x + 12, ry - 1), (x + 18, ry - 10), RV_TEXT, 2, cv2.LINE_AA)
        put_text(canvas, name, x + 26, ry, color=RV_TEXT, scale=0.4)
        put_text(canvas, topic, x + 175, ry, color=(110, 110, 110), scale=0.34,
                 width=w - 180)
    images = {"/fingerps/normal_map": cv2.cvtColor(data.normal_map, cv2.COLOR_RGB2BGR),
              "/fingerps/fingerprint": data.fingerprint,
              "/fingerps/depth": depth_as_rviz(data.depth_m),
              "/fingerps/image_raw": data.raw}
    panes = [d for d in displays if d["Class"].endswith("/Image") and d["Enabled"]]
    pane_top = top + tree_h + 4
    pane_h = (height - 4 - pane_top) // max(len(panes), 1)
    for i, display in enumerate(panes):
        rect = pane(display["Name"], (4, pane_top + i * pane_h, left_w, pane_h - 4))
        sub = (rect[0], rect[1], rect[2], rect[3])
        canvas[sub[1]:sub[1] + sub[3], sub[0]:sub[0] + sub[2]] = (0, 0, 0)
        fit_image(canvas, images[display["Topic"]["Value"]], sub)

    # the 3D view: the enabled point cloud display through the Orbit view
    view = manager["Views"]["Current"]
    vx, vy = left_w + 8, top
    vw, vh = width - left_w - right_w - 16, height - top - 4
    canvas[vy:vy + vh, vx:vx + vw] = rviz_bgr(manager["Global Options"]["Background Color"])
    camera, fov = rviz_orbit_camera(view)
    for display in displays:
        if display["Class"].endswith("/PointCloud2") and display["Enabled"]:
            assert display["Color Transformer"] == "Intensity"
            colours = rviz_rainbow(normalized(data.albedo),
                                   invert=bool(display["Invert Rainbow"]))
            splat(canvas, (vx, vy, vw, vh), data.points, colours, camera, fov,
                  int(display["Size (Pixels)"]))
            put_text(canvas, f"{display['Name']}: {display['Topic']['Value']}, "
                     f"{display['Color Transformer']} ({display['Channel Name']}, rainbow)",
                     vx + 8, vy + vh - 10, color=(200, 200, 200), scale=0.4)
    put_text(canvas, f"Fixed Frame: {manager['Global Options']['Fixed Frame']}", vx + 8,
             vy + 18, color=(200, 200, 200), scale=0.4)

    # right dock: the Views panel
    x, y, w, _ = pane("Views", (width - right_w - 4, top, right_w, 250))
    fields = [("Type", view["Value"]), ("Current View", view["Class"].split("/")[-1]),
              ("Distance", f"{view['Distance']} m"),
              ("Focal Point", ", ".join(str(view["Focal Point"][k]) for k in "XYZ")),
              ("Pitch", f"{view['Pitch']} rad"), ("Yaw", f"{view['Yaw']} rad"),
              ("Field of View", f"{view['Field of View']} rad"),
              ("Near Clip", f"{view['Near Clip Distance']} m"),
              ("Target Frame", view["Target Frame"])]
    for i, (key, value) in enumerate(fields):
        put_text(canvas, key, x + 8, y + 18 + 22 * i, color=RV_TEXT, scale=0.38)
        put_text(canvas, str(value), x + 100, y + 18 + 22 * i, color=(90, 90, 90), scale=0.36,
                 width=w - 104)
    return canvas


def depth_as_rviz(depth_m: np.ndarray) -> np.ndarray:
    """RViz's Image display of 32FC1 with Normalize Range: min..max of the image to 0..255
    (NaN, off the finger, is left out of the range and drawn black)."""
    finite = np.isfinite(depth_m)
    out = np.zeros(depth_m.shape, dtype=np.uint8)
    out[finite] = (normalized(depth_m[finite]) * 255).astype(np.uint8)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "viewing"),
                        help="folder of the two pictures (default docs/viewing)")
    args = parser.parse_args(argv)
    if not start_private_tool("render_viewing_pictures"):
        return 2
    data = capture()
    layout = json.loads((CONFIG / "foxglove_layout.json").read_text())
    rviz = yaml.safe_load((CONFIG / "fingerps.rviz").read_text())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, picture in (("foxglove_layout.png", foxglove_picture(layout, data)),
                          ("fingerps_rviz.png", rviz_picture(rviz, data))):
        path = out / name
        path.write_bytes(small_png(picture))
        print(f"{path}: {path.stat().st_size // 1024} KB")
    return 0


def small_png(picture: np.ndarray, *, limit_bytes: int = 280_000) -> bytes:
    """PNG of the picture under ``limit_bytes``: the levels of each channel are cut to a
    step of 8 (32 levels), coarser only if that is not enough."""
    for step in (8, 12, 16, 24):
        levels = np.clip((picture.astype(np.int16) // step) * step + step // 2, 0, 255)
        ok, png = cv2.imencode(".png", levels.astype(np.uint8),
                               [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if ok and len(png) <= limit_bytes:
            break
    return png.tobytes()


if __name__ == "__main__":
    sys.exit(main())
