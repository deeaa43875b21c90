"""demo: the whole fingerps graph on the simulated rig, end to end, with a summary.

Starts driver_node, calib_node, recon_node and recorder_node as separate processes, then,
from its own node: calibrates the flat field (white target) and the lights (shiny sphere)
through the calibration services, captures bursts of the simulated finger, receives the
reconstructions, measures the normals' angular error against the rig's ground truth, writes
a normal-map PNG, a depth PNG and a PLY point cloud, and stops the graph (SIGINT, so the
recorder finalises its bag). This is a command-line tool, so its options are arguments.

The summary reports the first burst's latency on its own line (it meets the warm-up; its
cloud is awaited before the next burst is requested) and the steady state over the bursts
after it, requested at ``--rate`` (throughput, latency median and p95;
``demo_figures``); ``--json`` prints the same figures as one JSON line on stdout (the summary
then on stderr), ``--figures FILE`` writes them to a file. A figure with nothing to measure
it on (no steady burst with ``--bursts 1``) is JSON null.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import rclpy
from ament_index_python.packages import get_package_prefix
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2

from fingerps_driver.demo_figures import Figure, ms, timing_figures
from fingerps_driver.errors import DemoError
from fingerps_driver.simulation import RigConfig, SimulatedRig
from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights, CaptureBurst
from fingerps_recon.photometric.angular_error import angular_error_deg, summarize_angular_error
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.surface.ply import write_ply
from fingerps_ros import qos, service_call, topics
from fingerps_ros.command_line import EXIT_FAILED, CommandLineTool
from fingerps_ros.image_conversion import image_to_array
from fingerps_ros.point_cloud_conversion import cloud_to_points
from fingerps_ros.privacy import use_localhost_discovery
from fingerps_ros.time_conversion import time_nanoseconds

# Sphere placements for the light calibration (optical frame, metres): with two or more the
# calibration also finds the LED positions, and reconstruction uses near lights.
SPHERE_PLACEMENTS = ((2.0e-3, -1.5e-3, 0.094), (-4.0e-3, 2.0e-3, 0.092),
                     (4.5e-3, 2.5e-3, 0.097))

BURSTS = 20
"""Finger bursts by default: 4 s at the rig's 5 bursts/s, 19 of them after the first for the
steady state's median and p95."""

TOOL = CommandLineTool("demo", bad_input=(), failed=(DemoError,), error_prefix="demo: ")
"""How the demo starts and ends (fingerps_ros.command_line): a bad ``FINGERPS_UMASK`` or
option is exit code 2; a step that fails (DemoError) is ``demo: <message>`` and exit code 1
(a DemoError is not bad input: the options were fine, the graph did not deliver)."""

GRAPH = (
    ("fingerps_driver", "driver_node"),
    ("fingerps_calib", "calib_node"),
    ("fingerps_recon", "recon_node"),
    ("fingerps_recon", "recorder_node"),
)


def executable(package: str, name: str) -> str:
    """Path of an installed node executable (what ``ros2 run package name`` runs)."""
    path = Path(get_package_prefix(package)) / "lib" / package / name
    if not path.is_file():
        raise DemoError(f"{path} is missing: build the workspace (make build)")
    return str(path)


@dataclass
class Received:
    """Outputs received from recon_node, by burst stamp (ns)."""

    normals: dict[int, np.ndarray] = field(default_factory=dict)
    depth: dict[int, np.ndarray] = field(default_factory=dict)
    normal_map: dict[int, np.ndarray] = field(default_factory=dict)
    clouds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    latency_ms: dict[int, float] = field(default_factory=dict)
    arrival: dict[int, float] = field(default_factory=dict)   # time.monotonic() of receipt
    # recon_node's bursts done, dropped, failed and incomplete so far (its /diagnostics)
    recon_counts: dict[str, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def settled(self) -> tuple[int, int]:
        """(outputs received whole, bursts recon_node has finished with in any way)."""
        with self.lock:
            whole = min(len(self.clouds), len(self.normals), len(self.depth),
                        len(self.normal_map))
            return whole, sum(self.recon_counts.values())


def call_service(client, request, *, timeout: float, what: str):
    """Call a service whose node another thread spins; return the response, or raise
    DemoError naming ``what``."""
    if not client.wait_for_service(timeout_sec=timeout):
        raise DemoError(f"{what}: service {client.srv_name} not available after "
                        f"{timeout:.0f} s; see the node's log above")
    response = service_call.call_service(client, request, timeout)
    if response is None:
        raise DemoError(f"{what}: no answer from {client.srv_name} within {timeout:.0f} s")
    return response


class DemoClient(Node):
    """Calls the graph's services and collects its outputs."""

    def __init__(self) -> None:
        super().__init__("demo", namespace=topics.NAMESPACE)
        self.received = Received()
        self.capture = self.create_client(CaptureBurst, topics.CAPTURE_BURST)
        self.cal_lights = self.create_client(CalibrateLights, topics.CALIBRATE_LIGHTS)
        self.cal_flat = self.create_client(CalibrateFlatField, topics.CALIBRATE_FLAT_FIELD)
        self.set_driver_params = self.create_client(SetParameters, "driver/set_parameters")
        r = self.received
        self.create_subscription(Image, topics.NORMALS, lambda m: self._keep(r.normals, m),
                                 qos.OUTPUT_QOS)
        self.create_subscription(Image, topics.DEPTH, lambda m: self._keep(r.depth, m),
                                 qos.OUTPUT_QOS)
        self.create_subscription(Image, topics.NORMAL_MAP,
                                 lambda m: self._keep(r.normal_map, m), qos.OUTPUT_QOS)
        self.create_subscription(PointCloud2, topics.POINTS, self._on_cloud, qos.OUTPUT_QOS)
        self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 10)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith("recon: reconstruction"):
                values = {kv.key: kv.value for kv in status.values}
                with self.received.lock:
                    self.received.recon_counts = {
                        key: int(values.get(key, 0)) for key in
                        ("bursts_done", "bursts_dropped", "bursts_failed", "bursts_incomplete")}

    def _keep(self, store: dict[int, np.ndarray], msg: Image) -> None:
        with self.received.lock:
            store[time_nanoseconds(msg.header.stamp)] = image_to_array(msg)

    def _on_cloud(self, msg: PointCloud2) -> None:
        stamp = time_nanoseconds(msg.header.stamp)
        with self.received.lock:
            self.received.latency_ms[stamp] = (time.time_ns() - stamp) / 1e6
            self.received.arrival[stamp] = time.monotonic()
            self.received.clouds[stamp] = cloud_to_points(msg)

    def call(self, client, request, *, timeout: float, what: str):
        """:func:`call_service` (the node is spun by another thread)."""
        return call_service(client, request, timeout=timeout, what=what)

    def set_scene(self, scene: str) -> None:
        """Put an object in front of the simulated camera (the driver's sim.scene)."""
        self._set_driver("sim.scene", ParameterValue(type=ParameterType.PARAMETER_STRING,
                                                     string_value=scene), f"placing the {scene}")

    def move_sphere(self, center_m: tuple[float, float, float]) -> None:
        """Move the simulated calibration sphere (the driver's sim.sphere_center)."""
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY,
                               double_array_value=list(center_m))
        self._set_driver("sim.sphere_center", value, "moving the sphere")

    def _set_driver(self, name: str, value: ParameterValue, what: str) -> None:
        request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=value)])
        response = self.call(self.set_driver_params, request, timeout=20.0, what=what)
        if not response.results[0].successful:
            raise DemoError(f"{what}: {response.results[0].reason}")


def wait_for_outputs(received: Received, expected: int, *, quiet_s: float) -> None:
    """Wait until ``expected`` bursts are reconstructed, or recon_node has finished with all
    of them (some dropped or failed) and their outputs are in, or nothing changed for
    ``quiet_s``."""
    last_count, last_change = -1, time.monotonic()
    while time.monotonic() - last_change < quiet_s:
        count, finished = received.settled()
        done = received.recon_counts.get("bursts_done", 0)
        if count >= expected or (finished >= expected and count >= done):
            return
        if count + finished != last_count:
            last_count, last_change = count + finished, time.monotonic()
        time.sleep(0.05)


def start_graph(log_dir: Path, node_args: dict[str, list[str]]) -> list[subprocess.Popen]:
    """Start the graph's nodes as separate processes, logging to ``log_dir``;
    ``node_args``: extra command-line arguments by executable name."""
    processes = []
    for package, name in GRAPH:
        args = [executable(package, name), *node_args.get(name, [])]
        log = open(log_dir / f"{name}.log", "w")
        processes.append(subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT))
        log.close()
    return processes


def stop_graph(processes: list[subprocess.Popen], *, timeout: float = 15.0) -> list[int]:
    """SIGINT every process (as Ctrl-C does), then wait; kill what does not stop."""
    for proc in processes:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    codes = []
    for proc in processes:
        try:
            codes.append(proc.wait(timeout=timeout))
        except subprocess.TimeoutExpired:
            proc.kill()
            codes.append(proc.wait())
    return codes


def write_outputs(out: Path, normals_ps: np.ndarray, mask: np.ndarray, depth: np.ndarray,
                  points: np.ndarray, intensity: np.ndarray, normal_map: np.ndarray) -> None:
    """normal_map.png (as published), normals_raw.png, depth.png (near = bright), cloud.ply."""
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "normal_map.png"), cv2.cvtColor(normal_map, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(out / "normals_raw.png"),
                cv2.cvtColor(normal_map_rgb(normals_ps, mask=mask), cv2.COLOR_RGB2BGR))
    finite = np.isfinite(depth)
    picture = np.zeros(depth.shape, dtype=np.uint8)
    if finite.any():
        near, far = np.percentile(depth[finite], [1, 99])
        scaled = (far - depth[finite]) / max(far - near, 1e-9)
        picture[finite] = np.clip(25 + 230 * scaled, 0, 255).astype(np.uint8)
    cv2.imwrite(str(out / "depth.png"), picture)
    write_ply(out / "cloud.ply", points, intensity=intensity)


def run(args: argparse.Namespace) -> int:
    """Run the demo; return the exit code."""
    out = Path(args.out)
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    rig = SimulatedRig(RigConfig())
    truth = rig.finger_truth()
    calibration_dir = out / "calibration"
    processes = start_graph(logs, {
        "recorder_node": ["--ros-args", "-p", f"bags_dir:={args.bags}"],
        "calib_node": ["--ros-args", "-p", f"calibration_dir:={calibration_dir}"],
        "recon_node": ["--ros-args", "-p", f"model:={args.model}"],
    })
    rclpy.init()
    node = DemoClient()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, name="demo_spin", daemon=True)
    spinner.start()
    timings: dict[str, float] = {}
    try:
        t0 = time.monotonic()
        node.set_scene("white_target")
        flat = node.call(node.cal_flat, CalibrateFlatField.Request(), timeout=60.0,
                         what="flat-field calibration")
        if not flat.success:
            raise DemoError(f"flat-field calibration failed: {flat.message}")
        timings["calibrate_flat_field_s"] = time.monotonic() - t0
        t0 = time.monotonic()
        node.set_scene("sphere")
        for i, center in enumerate(SPHERE_PLACEMENTS):
            node.move_sphere(center)
            lights = node.call(node.cal_lights, CalibrateLights.Request(
                sphere_radius=rig.config.sphere.radius_m, add_placement=i > 0),
                timeout=60.0, what=f"light calibration, sphere placement {i + 1}")
            if not lights.success:
                raise DemoError(f"light calibration failed: {lights.message}")
        timings["calibrate_lights_s"] = time.monotonic() - t0
        led_positions = np.array([[p.x, p.y, p.z] for p in lights.calibration.led_positions])
        led_err_mm = (1e3 * np.linalg.norm(led_positions - rig.led_positions_optical, axis=1)
                      if len(led_positions) else np.full(rig.led_count, np.nan))
        directions = optical_to_ps(np.array([[d.x, d.y, d.z]
                                             for d in lights.calibration.directions]))
        light_err = np.degrees(np.arccos(np.clip(
            np.sum(directions * rig.light_directions_ps(), axis=1), -1, 1)))
        node.set_scene("finger")
        time.sleep(0.5)  # let recon_node receive the transient-local calibration
        capture_ms, requested, stamps = [], [], []
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        for i in range(args.bursts):
            if i == 1:
                # The first burst meets the warm-up: its cloud is awaited before the steady
                # state starts, so that the bursts after it do not queue behind it.
                wait_for_outputs(node.received, 1, quiet_s=40.0)
                t_steady = time.monotonic()
            if i >= 1:  # at the rig's rate: burst i is requested at t_steady + (i - 1) / rate
                time.sleep(max(0.0, t_steady + (i - 1) * period - time.monotonic()))
            t0 = time.monotonic()
            response = node.call(node.capture, CaptureBurst.Request(), timeout=30.0,
                                 what="burst capture")
            if not response.success:
                raise DemoError(f"burst capture failed: {response.message}")
            capture_ms.append((time.monotonic() - t0) * 1e3)
            requested.append(t0)
            stamps.append(time_nanoseconds(response.burst.header.stamp))
        wait_for_outputs(node.received, args.bursts, quiet_s=40.0)
    finally:
        codes = stop_graph(processes)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()

    r = node.received
    if not r.clouds or not r.normals:
        raise DemoError(f"no reconstruction arrived; see {logs}/recon_node.log")
    errors = []
    for _, normals_optical in sorted(r.normals.items()):
        est = optical_to_ps(normals_optical)
        both = truth.mask & np.any(est != 0, axis=2)
        errors.append(summarize_angular_error(angular_error_deg(est, truth.normals_ps),
                                             mask=both))
    last = max(r.clouds)
    est = optical_to_ps(r.normals[last])
    mask = np.any(est != 0, axis=2)
    write_outputs(out, est, mask, r.depth[last], *r.clouds[last], r.normal_map[last])
    coverage = float((mask & truth.mask).sum() / truth.mask.sum())
    mae = float(np.mean([e.mean for e in errors]))
    with r.lock:
        timing = timing_figures(requested, stamps, dict(r.latency_ms), dict(r.arrival))
        dropped = r.recon_counts.get("bursts_dropped")
    figures: dict[str, Figure | str] = {
        "bursts_requested": args.bursts,
        "bursts_captured": len(capture_ms),
        "bursts_reconstructed": len(r.clouds),
        "recon_bursts_dropped": dropped,
        **timing,
        "e2e.mae_deg": mae,
        "capture_ms_median": float(np.median(capture_ms)),
        "normals_median_deg": float(np.mean([e.median for e in errors])),
        "normals_p95_deg": float(np.mean([e.p95 for e in errors])),
        "finger_coverage": coverage,
        "light_direction_error_deg_max": float(light_err.max()),
        "led_position_error_mm_max": float(led_err_mm.max()),
        "sphere_placements": len(SPHERE_PLACEMENTS),
        "model": args.model,
        **timings,
        "total_s": time.monotonic() - t_start,
    }
    # With --json, stdout is the one JSON line (for a script) and the summary goes to stderr.
    print_summary(figures, out, codes, stream=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(json_figures(figures), allow_nan=False), flush=True)
    if args.figures:
        Path(args.figures).write_text(
            json.dumps(json_figures(figures), indent=2, allow_nan=False) + "\n")
    bad = [name for (_, name), code in zip(GRAPH, codes, strict=True) if code != 0]
    if bad:
        TOOL.error(f"{', '.join(bad)} did not exit cleanly; see {logs}")
        return EXIT_FAILED
    return 0


def json_figures(figures: dict[str, Figure | str]) -> dict[str, Figure | str]:
    """The figures as strict JSON takes them: a NaN or infinite figure (e.g. the LED
    positions' error when the calibration found none) becomes None (null)."""
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v
            for k, v in figures.items()}


def print_summary(f: dict[str, Figure | str], out: Path, codes: list[int], *,
                  stream=sys.stdout) -> None:
    """The demo's summary, for people (to ``stream``)."""
    def line(text: str) -> None:
        print(text, file=stream)

    dropped = f["recon_bursts_dropped"]
    rate = f["e2e.bursts_per_s"]
    line(f"fingerps demo on the simulated rig (reconstruction model: {f['model']})")
    line(f"  bursts captured / reconstructed : {f['bursts_captured']} / "
         f"{f['bursts_reconstructed']}"
         + ("" if dropped is None else f" ({dropped} dropped by recon_node)"))
    line(f"  normals vs ground truth (finger): mean {f['e2e.mae_deg']:.2f} deg, median "
         f"{f['normals_median_deg']:.2f} deg, p95 {f['normals_p95_deg']:.2f} deg, "
         f"coverage {100 * f['finger_coverage']:.0f}%")
    line(f"  light calibration               : {f['sphere_placements']} sphere placements, "
         f"LED positions within {f['led_position_error_mm_max']:.1f} mm, directions within "
         f"{f['light_direction_error_deg_max']:.2f} deg of the truth")
    line(f"  capture (service round trip)    : median {f['capture_ms_median']:.0f} ms/burst")
    line(f"  first burst (warm-up) latency   : {ms(f['e2e.first_latency_ms'])}")
    steady = ("steady state" + (f", bursts 2-{f['bursts_captured']}"
                                if f["bursts_captured"] >= 2 else ""))
    line(f"  {steady:<32}: {f['steady_bursts_reconstructed']} of "
         f"{f['steady_bursts_captured']} reconstructed, throughput "
         + ("n/a" if rate is None else f"{rate:.2f} bursts/s"))
    line(f"  steady burst -> cloud latency   : median {ms(f['e2e.latency_ms_median'])}, "
         f"p95 {ms(f['e2e.latency_ms_p95'])}")
    line(f"  calibration                     : flat field "
         f"{f['calibrate_flat_field_s']:.1f} s, lights {f['calibrate_lights_s']:.1f} s")
    line(f"  outputs                         : {out}/normal_map.png, depth.png, cloud.ply")
    line(f"  node exit codes                 : {codes}; total {f['total_s']:.1f} s")


def _parser() -> argparse.ArgumentParser:
    """The demo's options."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    parser.add_argument("--bags", default="bags", help="where the session is recorded")
    parser.add_argument("--bursts", type=int, default=BURSTS,
                        help=f"finger bursts to capture (default {BURSTS}: the first, which "
                             "meets the warm-up, and the steady state after it)")
    parser.add_argument("--rate", type=float, default=5.0,
                        help="bursts requested per second (default 5, the paper's rig: a "
                             "burst within 0.2 s); 0 = back to back")
    parser.add_argument("--figures", help="also write the figures as JSON to this file")
    parser.add_argument("--json", action="store_true",
                        help="print the figures as one JSON line on stdout (the summary "
                             "then goes to stderr)")
    parser.add_argument("--model", choices=("lambert", "hk"), default="hk",
                        help="reflectance model of the reconstruction (default hk)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_driver demo``: through :data:`TOOL` (owner-only
    umask, the options, a DemoError as one line and exit code 1)."""
    options = _parser()

    def job(args: argparse.Namespace) -> int:
        if args.bursts < 1:
            options.error("--bursts must be at least 1")  # usage + error line, exit 2
        use_localhost_discovery()  # the graph it starts talks to this machine only
        return run(args)

    return TOOL.main(options, job, argv)


if __name__ == "__main__":
    raise SystemExit(main())
