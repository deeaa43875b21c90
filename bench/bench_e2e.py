"""The whole graph end to end on the simulated rig: the demo, and the graph as a kiosk runs it.

Every node is a separate process in a ROS domain of this benchmark's own (an id held with a
lock file, as the graph tests do) with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; ROS_HOME,
ROS_LOG_DIR and the calibration directory are in a temporary folder, so nothing from
``~/.ros`` is read. Wall-clock figures: they depend on what else the machine runs, so the
load average and the core count are printed with them.

The demo (``demo --bursts 10 --model hk``, requested at its default 5 bursts/s; median over
``DEMO_RUNS``):

- ``e2e.first_latency_ms``: the first burst's, burst stamp -> point cloud received by the
  demo's node (it meets the warm-up: the calibration prepared for the camera, cold memory);
- ``e2e.bursts_per_s``: the steady state's throughput, the clouds of the bursts after the
  first / seconds from the second request to the last of them;
- ``e2e.latency_ms_median``, ``e2e.latency_ms_p95``: burst stamp -> point cloud received,
  over the bursts after the first;
- ``e2e.mae_deg``: mean angular error of the normals against ground truth in the finger.

The kiosk (``e2e.hk.*``, ``e2e.hk10.*``, ``e2e.first_cloud_s``, ``e2e.hk_print_rec.*``):
driver_node (simulated rig, continuous capture), calib_node (``calibration_dir`` in the
temporary folder) and recon_node (``model:=hk``). The benchmark's own node (another process
than recon) calibrates the flat field (white target) and the lights (shiny sphere, three
placements) through the services as the demo does, with the driver at ``rate`` 0, then puts
the finger in front of the camera and sets the driver's ``rate`` to 5 bursts/s at run time
(a parameter service call). It subscribes to ``/fingerps/burst`` (the QoS it is published
with; serialized, only the header stamp is read) to know every burst published, and to
``/fingerps/points`` (PointCloud2, deserialized as any consumer would). recon_node copies
the burst's header into its outputs, and the burst's header is that of its last frame:
``header.stamp`` is the wall clock (``time.time_ns`` in driver_node) when the board
acknowledged the last LED's switch, just before that frame's grab; so a cloud is matched to
its burst by stamp, and its latency covers the last frame's exposure and grab, publishing
the burst, transport, the queue, the reconstruction, publishing and transport of the outputs
and deserializing the cloud.

After a warm-up (the first cloud, up to ``FIRST_CLOUD_TIMEOUT_S``; then 5 clouds or 10 s),
windows of ``WINDOW_S`` = 60 s, each with the same five figures under its prefix:

- ``<prefix>.bursts_per_s``: clouds received in the window (by arrival time) / its length;
- ``<prefix>.published_per_s``: bursts the driver published in the window (stamp inside it)
  / its length (what it delivered against the rate asked for: the driver may not keep up);
- ``<prefix>.lost``: bursts published in the window (stamp inside it) whose cloud never
  arrived (recon's queue dropped them, or they failed), counted after a grace period that
  ends when every one has its cloud or no cloud of the window arrived for a while;
- ``<prefix>.latency_ms_median``, ``<prefix>.latency_ms_p95``: received (``time.time_ns`` in
  the subscriber's callback) - ``header.stamp``, over the clouds of the window's bursts;
- ``<prefix>.cpu_cores.<node>``: CPU time (user + system, from /proc) each node's processes
  used in the window / its length, in cores (``bench``: this process, the observer): where
  the machine's cores go.

The windows, in this order on one graph (after a rate change ``RATE_SETTLE_S`` to settle):

- ``e2e.hk.*``: the driver at 5 bursts/s (the rig's rate), right after the warm-up;
- ``e2e.hk10.*``: the driver at ``FAST_RATE_HZ`` = 10 bursts/s;
- ``e2e.hk.max_bursts_per_s``: the highest rate the driver delivered with nothing lost: the
  largest ``published_per_s`` of a lossless window among the 5/s and 10/s windows and a
  sweep of ``SWEEP_WINDOW_S`` windows: if 10/s lost nothing (and the driver delivered at
  least 90 % of it), up through ``SWEEP_UP`` until a window loses a burst or the driver
  delivers less than 90 % of the rate asked for; if 5/s lost nothing but 10/s did, the
  rates of ``SWEEP_BETWEEN``; if 5/s lost bursts, down through ``SWEEP_DOWN`` to the first
  lossless window (0 if none).
- ``e2e.first_cloud_s``: with the driver capturing at 5/s and calib_node holding the
  calibration (transient-local), recon_node is stopped (SIGINT, waited for) and launched
  again; seconds from launching its process to the first PointCloud2 received; median of
  ``FIRST_CLOUD_STARTS`` starts on the built workspace (caches as the build left them).
- ``e2e.hk_print_rec.*``: the kiosk with the print and the recorder: recorder_node
  (fingerps_recon; ``bags_dir`` in the temporary folder, its defaults otherwise: the
  session topics with the outputs, so the print too) started, recon_node launched again
  with ``model:=hk`` and ``fingerprint:=true``; after the warm-up (its first cloud and
  print, then 5 clouds or 10 s) a window at ``PRINT_RATE_HZ`` = 5 bursts/s with the five
  figures above, and:

  - ``e2e.hk_print_rec.prints``: the window's bursts whose print (``/fingerps/fingerprint``,
    mono8, matched by stamp; serialized, only the header stamp is read) arrived;
  - ``e2e.hk_print_rec.print_latency_ms_median``: print received - ``header.stamp``;
  - ``e2e.hk_print_rec.recorder_not_written``: messages the recorder subscribed to and did
    not write over its whole recording (warm-up, window and stop): the finished bag's count
    (metadata.yaml ``custom_data`` ``fingerps.not_written``, by topic and reason in the
    printed line), else its last /diagnostics' ``not_written`` (left out if neither).

Targets (for the AVX2 pass's figures on 2 cores): ``e2e.hk10.lost`` = 0 with
``e2e.hk10.published_per_s`` ~ 10, ``e2e.hk10.latency_ms_median`` <= 100 ms,
``e2e.hk10.latency_ms_p95`` <= 150 ms; ``e2e.hk.max_bursts_per_s`` reported;
``e2e.hk_print_rec.lost`` = 0 (and ``prints`` = every burst of the window),
``e2e.hk_print_rec.latency_ms_median`` <= 150 ms; ``e2e.first_cloud_s`` <= 10.

Alone: ``python bench/bench_e2e.py`` (``--no-demo`` skips the demo runs; ``--only
kiosk10,print`` runs only those scenarios, of ``SCENARIOS``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fingerps_driver.demo import SPHERE_PLACEMENTS, call_service, executable
from fingerps_driver.errors import DemoError
from fingerps_ros.time_conversion import time_nanoseconds

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # ros_domain
from figures_report import exit_codes, print_figures
from polling import poll_until
from ros_domain import domain_env, own_ros_domain

DEMO_RUNS = 3
DEMO_NAMES = ("e2e.first_latency_ms", "e2e.bursts_per_s", "e2e.latency_ms_median",
              "e2e.latency_ms_p95", "e2e.mae_deg")

SCENARIOS = ("demo", "kiosk", "kiosk10", "sweep", "first_cloud", "print")
"""What ``--only`` chooses from: the demo runs; the graph's 5/s window (``e2e.hk.*``), 10/s
window (``e2e.hk10.*``), rate sweep (``e2e.hk.max_bursts_per_s``; it needs both windows),
restarts (``e2e.first_cloud_s``) and print-and-recorder window (``e2e.hk_print_rec.*``)."""
GRAPH_SCENARIOS = SCENARIOS[1:]

RATE_HZ = 5.0                  # the rig's burst rate: the kiosk's setting
FAST_RATE_HZ = 10.0            # the real-time target's rate
PRINT_RATE_HZ = 5.0            # the kiosk with the print and the recorder
WINDOW_S = 60.0
WARM_UP_CLOUDS, WARM_UP_MAX_S = 5, 10.0
FIRST_CLOUD_TIMEOUT_S = 120.0  # a first reconstruction that compiles kernels is slow
RATE_SETTLE_S = 3.0            # after the driver's rate is changed, before a window
SWEEP_UP = (12.5, 15.0, 20.0)  # beyond a lossless 10/s window
SWEEP_BETWEEN = (7.5,)         # after a lossless 5/s and a lossy 10/s window
SWEEP_DOWN = (2.5, 1.0)        # after a lossy 5/s window
SWEEP_WINDOW_S = 15.0
DELIVERED_FRACTION = 0.9       # below this share of the rate asked for, the driver cannot
FIRST_CLOUD_STARTS = 3
GRACE_MAX_S = 20.0             # longest wait for a window's last clouds
PRINT_AFTER_CLOUD_S = 1.0      # and for the last prints once the clouds are in
STOP_TIMEOUT_S = 20.0
RECORDER_STOP_TIMEOUT_S = 60.0  # the recorder drains its queue and finishes its bag


class BenchError(Exception):
    """The benchmark could not complete; the message says which step and where the logs are."""


def graph_env(domain_id: int, home: Path) -> dict[str, str]:
    """The node processes' environment: ``domain_env``, ROS_HOME and ROS_LOG_DIR in ``home``."""
    return domain_env(domain_id, ROS_HOME=str(home), ROS_LOG_DIR=str(home / "log"),
                      PYTHONUNBUFFERED="1", RCUTILS_COLORIZED_OUTPUT="0")


def load_line() -> str:
    one, five, fifteen = os.getloadavg()
    return (f"load average {one:.2f} {five:.2f} {fifteen:.2f} (1/5/15 min) on "
            f"{os.cpu_count()} cores")


# ---------------------------------------------------------------------------- the demo
def run_demo(env: dict[str, str], runs: int) -> dict[str, float]:
    """The demo's figures, median over ``runs`` runs."""
    demo = executable("fingerps_driver", "demo")
    collected: dict[str, list[float]] = {name: [] for name in DEMO_NAMES}
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            figures_path = Path(tmp) / "figures.json"
            subprocess.run([demo, "--out", f"{tmp}/out", "--bags", f"{tmp}/bags",
                            "--bursts", "10", "--model", "hk", "--figures", str(figures_path)],
                           check=True, env={**env, "ROS_HOME": tmp, "ROS_LOG_DIR": tmp},
                           stdout=subprocess.DEVNULL)
            figures = json.loads(figures_path.read_text())
        for name in DEMO_NAMES:
            if figures[name] is not None:  # null: nothing to measure it on in that run
                collected[name].append(float(figures[name]))
    return {name: float(np.median(values)) for name, values in collected.items() if values}


# ---------------------------------------------------------------------------- processes
def cpu_seconds_from_stat(fields: list[str]) -> float:
    """CPU seconds (user + system) of a process from its /proc/<pid>/stat fields after the
    command name ([state, ppid, ...]: utime and stime are the 12th and 13th)."""
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def own_cpu_seconds() -> float:
    """CPU seconds (user + system) this process has used: the benchmark's observer."""
    times = os.times()
    return times.user + times.system


class Graph:
    """Node processes by executable name; each logs to ``<log_dir>/<name>_<n>.log``."""

    def __init__(self, log_dir: Path, env: dict[str, str]) -> None:
        self.log_dir, self.env = log_dir, env
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        self._starts = 0

    def start(self, package: str, name: str, *args: str) -> None:
        self._starts += 1
        log_path = self.log_dir / f"{name}_{self._starts}.log"
        with open(log_path, "wb") as log:
            self.procs[name] = subprocess.Popen(
                [executable(package, name), "--ros-args", *args], stdin=subprocess.DEVNULL,
                stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)
        self.logs[name] = log_path

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds (user + system) each node's processes (its session: the node and
        anything it started) have used so far, from /proc; this process's as ``bench``
        (the observer's subscriptions and deserialization)."""
        groups = {proc.pid: name for name, proc in self.procs.items()}
        used = dict.fromkeys(groups.values(), 0.0)
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue  # gone meanwhile
            name = groups.get(int(fields[3]))  # the session id (field 6 of stat)
            if name is not None:
                used[name] += cpu_seconds_from_stat(fields)
        used["bench"] = own_cpu_seconds()
        return used

    def check_running(self) -> None:
        for name, proc in self.procs.items():
            if proc.poll() is not None:
                raise BenchError(f"{name} exited with {proc.returncode}:\n{self.tail(name)}")

    def tail(self, name: str, lines: int = 15) -> str:
        text = self.logs[name].read_text(errors="replace").splitlines()
        return "\n".join(f"  | {line}" for line in text[-lines:])

    def stop(self, name: str, timeout: float = STOP_TIMEOUT_S) -> int:
        """SIGINT (as Ctrl-C), wait; SIGKILL of its process group if it does not stop."""
        proc = self.procs.pop(name)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            print(f"bench_e2e: {name} ignored SIGINT for {timeout:.0f} s; killed",
                  file=sys.stderr)
            code = None
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # and anything it started
        except (ProcessLookupError, PermissionError):
            pass
        return proc.wait() if code is None else code

    def stop_all(self) -> dict[str, int]:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        return {name: self.stop(name, RECORDER_STOP_TIMEOUT_S if name == "recorder_node"
                                else STOP_TIMEOUT_S)
                for name in list(self.procs)[::-1]}


# ---------------------------------------------------------------------------- observer
@dataclass
class Seen:
    """What the observer received. Stamps and receipt times in ns (wall clock)."""

    bursts: dict[int, int] = field(default_factory=dict)         # stamp -> received
    clouds: dict[int, int] = field(default_factory=dict)         # stamp -> received
    prints: dict[int, int] = field(default_factory=dict)         # stamp -> received
    cloud_mono: list[float] = field(default_factory=list)        # time.monotonic() of each
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


def _burst_stamp(serialized: bytes) -> int:
    """header.stamp of a serialized message that starts with its std_msgs/Header (a Burst,
    an Image): CDR (4-byte encapsulation), then int32 sec and uint32 nanosec, little-endian
    as the encapsulation says."""
    endian = "<" if serialized[1] & 1 else ">"
    sec, nanosec = struct.unpack_from(endian + "iI", serialized, 4)
    return sec * 1_000_000_000 + nanosec


class Observer:
    """The benchmark's node: calls the services, sets parameters, receives bursts and clouds."""

    def __init__(self, domain_id: int, name: str = "bench_e2e") -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rcl_interfaces.srv import SetParameters
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import Image, PointCloud2

        from fingerps_msgs.msg import Burst
        from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights
        from fingerps_ros import qos, topics

        self.seen = Seen()
        saved = {k: os.environ.get(k) for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE",
                                                 "ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY")}
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ.pop("ROS_STATIC_PEERS", None)
        os.environ.pop("ROS_LOCALHOST_ONLY", None)
        self.context = Context()
        try:
            rclpy.init(context=self.context, domain_id=domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        node = self.node = rclpy.create_node(name, namespace=topics.NAMESPACE,
                                             context=self.context)
        self.cal_flat = node.create_client(CalibrateFlatField, topics.CALIBRATE_FLAT_FIELD)
        self.cal_lights = node.create_client(CalibrateLights, topics.CALIBRATE_LIGHTS)
        self.driver_params = node.create_client(SetParameters, "driver/set_parameters")
        node.create_subscription(Burst, topics.BURST, self._on_burst, qos.BURST_QOS, raw=True)
        node.create_subscription(PointCloud2, topics.POINTS, self._on_cloud, qos.OUTPUT_QOS)
        node.create_subscription(Image, topics.FINGERPRINT, self._on_print, qos.OUTPUT_QOS,
                                 raw=True)
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(node)
        self._spinner = threading.Thread(target=self.executor.spin, name="bench_e2e_spin",
                                         daemon=True)
        self._spinner.start()

    def close(self) -> None:
        import rclpy
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._spinner.join(timeout=5.0)

    # --------------------------------------------------------------- callbacks
    def _on_burst(self, serialized: bytes) -> None:
        now = time.time_ns()
        with self.seen.lock:
            self.seen.bursts[_burst_stamp(serialized)] = now

    def _on_cloud(self, msg) -> None:
        now = time.time_ns()
        mono = time.monotonic()
        stamp = time_nanoseconds(msg.header.stamp)
        with self.seen.lock:
            self.seen.clouds[stamp] = now
            self.seen.cloud_mono.append(mono)

    def _on_print(self, serialized: bytes) -> None:
        now = time.time_ns()
        with self.seen.lock:
            self.seen.prints[_burst_stamp(serialized)] = now

    def _on_diag(self, msg) -> None:
        with self.seen.lock:
            for status in msg.status:
                self.seen.diagnostics[status.name] = {kv.key: kv.value for kv in status.values}

    # --------------------------------------------------------------- services
    def call(self, client, request, *, timeout: float, what: str):
        return call_service(client, request, timeout=timeout, what=what)

    def set_driver(self, name: str, value: object) -> None:
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        # typed from the value: a str, a float, a tuple of floats (a double array)
        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()])
        response = self.call(self.driver_params, request, timeout=20.0,
                             what=f"setting the driver's {name}")
        if not response.results[0].successful:
            raise BenchError(f"setting the driver's {name}: {response.results[0].reason}")

    def calibrate(self) -> None:
        """Flat field (white target), then the lights (sphere, three placements)."""
        from fingerps_driver.simulation import RigConfig
        from fingerps_msgs.srv import CalibrateFlatField, CalibrateLights
        self.set_driver("sim.scene", "white_target")
        flat = self.call(self.cal_flat, CalibrateFlatField.Request(), timeout=60.0,
                         what="flat-field calibration")
        if not flat.success:
            raise BenchError(f"flat-field calibration failed: {flat.message}")
        self.set_driver("sim.scene", "sphere")
        for i, center in enumerate(SPHERE_PLACEMENTS):
            self.set_driver("sim.sphere_center", center)
            lights = self.call(self.cal_lights, CalibrateLights.Request(
                sphere_radius=RigConfig().sphere.radius_m, add_placement=i > 0),
                timeout=60.0, what=f"light calibration, placement {i + 1}")
            if not lights.success:
                raise BenchError(f"light calibration failed: {lights.message}")
        self.set_driver("sim.scene", "finger")

    # --------------------------------------------------------------- waiting
    def recon_counts(self) -> dict[str, int]:
        """recon_node's burst counters from its last diagnostics (published once a second,
        so a window's differences are a cross-check of ``lost``, not exact)."""
        with self.seen.lock:
            values = self.seen.diagnostics.get("recon: reconstruction", {})
            return {key.removeprefix("bursts_"): int(values[key])
                    for key in ("bursts_done", "bursts_dropped", "bursts_failed")
                    if values.get(key, "").isdigit()}

    def clouds_since(self, mono: float) -> list[float]:
        with self.seen.lock:
            return [t for t in self.seen.cloud_mono if t >= mono]


def wait_until(condition: Callable[[], object], *, timeout: float, what: str,
               graph: Graph) -> None:
    """Poll ``condition`` (``polling.poll_until``) while the graph runs; BenchError after
    ``timeout``, or at once if a node of the graph has exited."""
    def holds() -> object:
        graph.check_running()
        return condition()

    if not poll_until(holds, timeout):
        raise BenchError(f"timed out after {timeout:.0f} s waiting for {what}")


@dataclass(frozen=True)
class Window:
    """One measuring window at a driver rate."""

    rate: float
    seconds: float
    published: int               # bursts with a stamp in the window
    received: int                # clouds that arrived in the window
    lost: int                    # published bursts whose cloud never arrived
    latency_ms: tuple[float, ...]
    recon_counts: dict[str, int]  # recon's diagnostics counters over the window (about)
    recon_stages: dict[str, str] = field(default_factory=dict)  # its stage medians, ms
    prints: int = 0              # the window's bursts whose print arrived (fingerprint topic)
    print_latency_ms: tuple[float, ...] = ()
    cpu_cores: dict[str, float] = field(default_factory=dict)  # CPU used per process / s

    @property
    def published_per_s(self) -> float:
        return self.published / self.seconds

    @property
    def bursts_per_s(self) -> float:
        return self.received / self.seconds

    def line(self) -> str:
        lat = (f"latency median {np.median(self.latency_ms):.0f} ms, p95 "
               f"{np.percentile(self.latency_ms, 95):.0f} ms" if self.latency_ms
               else "no cloud")
        return (f"rate {self.rate:5.1f}/s for {self.seconds:.0f} s: published "
                f"{self.published_per_s:5.2f}/s, clouds {self.bursts_per_s:5.2f}/s, lost "
                f"{self.lost}/{self.published}, {lat}; recon's diagnostics: "
                + ", ".join(f"{k} {v}" for k, v in self.recon_counts.items())
                + (f"; prints {self.prints}/{self.published}, print latency median "
                   f"{np.median(self.print_latency_ms):.0f} ms" if self.print_latency_ms
                   else "")
                + ("; recon's stage medians (ms): " + ", ".join(
                    f"{k.removesuffix('_ms')} {v}" for k, v in self.recon_stages.items())
                   if self.recon_stages else "")
                + ("; CPU (cores): " + ", ".join(
                    f"{k} {v:.2f}" for k, v in self.cpu_cores.items())
                   if self.cpu_cores else ""))


def measure(observer: Observer, graph: Graph, rate: float, seconds: float,
            tick: Callable[[], None] | None = None) -> Window:
    """Count bursts and clouds over ``seconds``, then wait for the window's last clouds;
    ``tick`` (if given) is called every 0.2 s of the window (the soak samples with it)."""
    counts_before = observer.recon_counts()
    cpu_before = graph.cpu_seconds()
    t0 = time.time_ns()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        graph.check_running()
        if tick is not None:
            tick()
        time.sleep(min(0.2, max(end - time.monotonic(), 0.0)))
    t1 = time.time_ns()
    cpu_after = graph.cpu_seconds()
    cpu_cores = {name: (cpu_after[name] - cpu_before[name]) / ((t1 - t0) / 1e9)
                 for name in cpu_after if name in cpu_before}
    seen = observer.seen
    # Grace: a burst stamped just before t1 is published a few ms later; its cloud later
    # still. Done when every burst of the window has its cloud, or when no cloud of the
    # window arrived for `quiet` (a cloud of a queued burst comes within a reconstruction).
    grace_end = time.monotonic() + GRACE_MAX_S
    time.sleep(0.5)
    last_count, last_change = -1, time.monotonic()
    while True:
        with seen.lock:
            window = [s for s in seen.bursts if t0 <= s < t1]
            done = {s: seen.clouds[s] for s in window if s in seen.clouds}
        latency = [(done[s] - s) / 1e6 for s in done]
        quiet = max(1.5, 2.5 * max(latency, default=0.0) / 1e3)
        if len(done) != last_count:
            last_count, last_change = len(done), time.monotonic()
        if (len(done) == len(window) or time.monotonic() - last_change > quiet
                or time.monotonic() > grace_end):
            break
        time.sleep(0.05)
    with seen.lock:
        printing = bool(seen.prints)
    if printing:
        time.sleep(PRINT_AFTER_CLOUD_S)  # a burst's print is published after its cloud
    with seen.lock:
        received = sum(1 for t in seen.clouds.values() if t0 <= t < t1)
        printed = {s: seen.prints[s] for s in window if s in seen.prints}
    counts_after = observer.recon_counts()
    counts = {k: counts_after[k] - counts_before.get(k, 0) for k in counts_after}
    with seen.lock:
        values = seen.diagnostics.get("recon: reconstruction", {})
        stages = {k: v for k, v in values.items() if k.endswith("_ms")}
    return Window(rate, (t1 - t0) / 1e9, len(window), received, len(window) - len(done),
                  tuple(latency), counts, stages, len(printed),
                  tuple((printed[s] - s) / 1e6 for s in printed), cpu_cores)


# ---------------------------------------------------------------------------- the kiosk
def window_figures(prefix: str, w: Window) -> dict[str, float]:
    """A window's figures under ``<prefix>.``: throughput, delivered rate, lost, latency."""
    return {
        f"{prefix}.bursts_per_s": w.bursts_per_s,
        f"{prefix}.published_per_s": w.published_per_s,
        f"{prefix}.lost": float(w.lost),
        f"{prefix}.latency_ms_median": (float(np.median(w.latency_ms)) if w.latency_ms
                                        else float("nan")),
        f"{prefix}.latency_ms_p95": (float(np.percentile(w.latency_ms, 95)) if w.latency_ms
                                     else float("nan")),
        **{f"{prefix}.cpu_cores.{name}": used for name, used in w.cpu_cores.items()},
    }


def warm_up(observer: Observer, graph: Graph, since: float, what: str,
            prints: bool = False) -> float:
    """Wait for the first cloud after ``since`` (and its print if ``prints``), then 5 clouds
    or 10 s; seconds from ``since`` to the first cloud."""
    since_ns = time.time_ns() - int((time.monotonic() - since) * 1e9)  # on the wall clock

    def first() -> bool:
        if not observer.clouds_since(since):
            return False
        with observer.seen.lock:
            return not prints or any(t >= since_ns for t in observer.seen.prints.values())

    wait_until(first, timeout=FIRST_CLOUD_TIMEOUT_S, what=what, graph=graph)
    t_first = observer.clouds_since(since)[0]
    wait_until(lambda: len(observer.clouds_since(t_first)) >= WARM_UP_CLOUDS
               or time.monotonic() - t_first > WARM_UP_MAX_S, timeout=WARM_UP_MAX_S + 5,
               what="the warm-up", graph=graph)
    return t_first - since


def at_rate(observer: Observer, graph: Graph, rate: float, seconds: float) -> Window:
    """The driver's ``rate`` set, ``RATE_SETTLE_S`` to settle, a window of ``seconds``."""
    observer.set_driver("rate", rate)
    time.sleep(RATE_SETTLE_S)
    return measure(observer, graph, rate, seconds)


def sweep(observer: Observer, graph: Graph, main: Window, fast: Window,
          lines: list[str]) -> float:
    """``e2e.hk.max_bursts_per_s`` from the 5/s and 10/s windows and short windows beyond
    them (see the module docstring)."""
    best = max((w.published_per_s for w in (main, fast) if w.lost == 0), default=0.0)
    if fast.lost == 0:  # up from 10/s while nothing is lost and the driver keeps up
        rates = SWEEP_UP if fast.published_per_s >= DELIVERED_FRACTION * FAST_RATE_HZ else ()
        up = True
    elif main.lost == 0:  # between the two
        rates = SWEEP_BETWEEN if main.published_per_s >= DELIVERED_FRACTION * RATE_HZ else ()
        up = True
    else:  # down from 5/s to the first lossless rate
        rates, up = SWEEP_DOWN, False
    for rate in rates:
        w = at_rate(observer, graph, rate, SWEEP_WINDOW_S)
        lines.append(f"sweep: {w.line()}")
        if w.lost == 0:
            best = max(best, w.published_per_s)
        if up and (w.lost or w.published_per_s < DELIVERED_FRACTION * rate):
            break
        if not up and w.lost == 0:
            break
    return best


def recorder_status(observer: Observer) -> dict[str, str]:
    """The recorder's last /diagnostics values (status ``<node>: recording``)."""
    with observer.seen.lock:
        for name, values in observer.seen.diagnostics.items():
            if name.endswith(": recording"):
                return dict(values)
    return {}


def bag_not_written(bags_dir: Path) -> tuple[int, dict, int] | None:
    """(messages not written, by topic and reason, messages written) of the finished bag in
    ``bags_dir`` (metadata.yaml ``custom_data`` ``fingerps.not_written``), None if no
    finished bag says it."""
    import yaml
    metas = sorted(bags_dir.glob("*/metadata.yaml")) if bags_dir.is_dir() else []
    if not metas:
        return None
    info = yaml.safe_load(metas[-1].read_text())["rosbag2_bagfile_information"]
    custom = (info.get("custom_data") or {}).get("fingerps.not_written")
    if custom is None:
        return None
    by_topic = json.loads(custom)
    return (sum(sum(reasons.values()) for reasons in by_topic.values()), by_topic,
            int(info.get("message_count", 0)))


def run_print_recorder(observer: Observer, graph: Graph, home: Path,
                       lines: list[str]) -> dict[str, float]:
    """The ``e2e.hk_print_rec.*`` figures: the recorder started, recon_node launched again
    with ``fingerprint:=true``, warm-up, a window at 5/s, the recorder stopped."""
    prefix = "e2e.hk_print_rec"
    observer.set_driver("rate", PRINT_RATE_HZ)
    bags_dir = home / "bags"
    graph.start("fingerps_recon", "recorder_node", "-p", f"bags_dir:={bags_dir}")
    graph.stop("recon_node")
    time.sleep(1.0)  # clouds in flight from the stopped process arrive before
    t_launch = time.monotonic()
    graph.start("fingerps_recon", "recon_node", "-p", "model:=hk", "-p", "fingerprint:=true")
    first = warm_up(observer, graph, t_launch, "the first cloud and print of recon_node "
                    "with fingerprint:=true", prints=True)
    lines.append(f"print+recorder: recon_node (fingerprint:=true) start -> first cloud "
                 f"{first:.1f} s; recorder into {bags_dir}")
    w = at_rate(observer, graph, PRINT_RATE_HZ, WINDOW_S)
    lines.append(f"print+recorder: {w.line()}")
    figures = window_figures(prefix, w)
    figures[f"{prefix}.prints"] = float(w.prints)
    figures[f"{prefix}.print_latency_ms_median"] = (
        float(np.median(w.print_latency_ms)) if w.print_latency_ms else float("nan"))
    status = recorder_status(observer)
    observer.set_driver("rate", 0.0)  # the recorder finishes what it has
    code = graph.stop("recorder_node", RECORDER_STOP_TIMEOUT_S)
    bag = bag_not_written(bags_dir)
    if bag is not None:
        not_written, by_topic, written = bag
        lines.append(f"print+recorder: recorder exited {code}; its bag: {written} messages "
                     f"written, not written {by_topic or 'none'}")
        figures[f"{prefix}.recorder_not_written"] = float(not_written)
    elif status.get("not_written", "").isdigit():
        lines.append(f"print+recorder: recorder exited {code} without a finished bag; its "
                     f"last diagnostics: received {status.get('messages_received')}, written "
                     f"{status.get('messages_written')}, not written {status['not_written']}")
        figures[f"{prefix}.recorder_not_written"] = float(status["not_written"])
    else:
        lines.append(f"print+recorder: recorder exited {code}; no count of messages not "
                     "written (no finished bag, no diagnostics)")
    return figures


def run_kiosk(env: dict[str, str], domain_id: int, home: Path,
              only: frozenset[str] = frozenset(GRAPH_SCENARIOS)) -> dict[str, float]:
    """The e2e.hk.*, e2e.hk10.*, e2e.hk_print_rec.* figures and e2e.first_cloud_s of the
    scenarios in ``only`` (see the module docstring)."""
    if "sweep" in only:
        only = only | {"kiosk", "kiosk10"}
    log_dir = home / "node_logs"
    log_dir.mkdir()
    graph = Graph(log_dir, env)
    observer: Observer | None = None
    lines: list[str] = []
    figures: dict[str, float] = {}
    try:
        graph.start("fingerps_driver", "driver_node", "-p", "rate:=0.0")
        graph.start("fingerps_calib", "calib_node", "-p",
                    f"calibration_dir:={home / 'calibration'}")
        graph.start("fingerps_recon", "recon_node", "-p", "model:=hk")
        observer = Observer(domain_id)
        t_cal = time.monotonic()
        observer.calibrate()
        lines.append(f"calibration (flat field, 3 sphere placements): "
                     f"{time.monotonic() - t_cal:.1f} s")

        # Warm-up at the kiosk's rate: the first cloud, then 5 clouds or 10 s.
        observer.set_driver("rate", RATE_HZ)
        first = warm_up(observer, graph, time.monotonic(), "the first point cloud")
        lines.append(f"first cloud {first:.1f} s after the rate was set")

        t0 = time.monotonic()
        if "kiosk" in only:
            main = measure(observer, graph, RATE_HZ, WINDOW_S)
            lines.append(f"5/s: {main.line()}")
            figures.update(window_figures("e2e.hk", main))
        if "kiosk10" in only:
            fast = at_rate(observer, graph, FAST_RATE_HZ, WINDOW_S)
            lines.append(f"10/s: {fast.line()}")
            figures.update(window_figures("e2e.hk10", fast))
        if "sweep" in only:
            figures["e2e.hk.max_bursts_per_s"] = sweep(observer, graph, main, fast, lines)
        lines.append(f"windows and sweep: {time.monotonic() - t0:.0f} s")

        if "first_cloud" in only:  # recon_node launched again while the driver runs at 5/s
            observer.set_driver("rate", RATE_HZ)
            starts = []
            for _ in range(FIRST_CLOUD_STARTS):
                graph.stop("recon_node")
                time.sleep(1.0)  # clouds in flight from the stopped process arrive before
                t_launch = time.monotonic()
                graph.start("fingerps_recon", "recon_node", "-p", "model:=hk")
                wait_until(lambda t=t_launch: observer.clouds_since(t),
                           timeout=FIRST_CLOUD_TIMEOUT_S,
                           what="the first cloud of a restarted recon_node", graph=graph)
                starts.append(observer.clouds_since(t_launch)[0] - t_launch)
            lines.append("recon_node start -> first cloud: "
                         + ", ".join(f"{s:.1f}" for s in starts) + " s")
            figures["e2e.first_cloud_s"] = float(np.median(starts))

        if "print" in only:
            t0 = time.monotonic()
            figures.update(run_print_recorder(observer, graph, home, lines))
            lines.append(f"print+recorder: {time.monotonic() - t0:.0f} s")
    except (BenchError, DemoError) as exc:  # a step failed: say it with the nodes' logs
        logs = "\n".join(f"{name}:\n{graph.tail(name)}" for name in graph.logs)
        raise BenchError(f"{exc}\n{logs}") from None
    finally:
        if observer is not None:
            observer.close()
        codes = graph.stop_all()
        if any(codes.values()):
            lines.append(f"exit codes: {codes}")
        for line in lines:
            print(f"  kiosk: {line}")
    return figures


def run(*, demo_runs: int = DEMO_RUNS,
        only: Collection[str] = SCENARIOS) -> dict[str, float]:
    """The figures of the scenarios in ``only`` (:data:`SCENARIOS`; the demo's only if
    ``demo_runs``)."""
    t_start = time.monotonic()
    graph_only = frozenset(only) & frozenset(GRAPH_SCENARIOS)
    figures: dict[str, float] = {}
    with own_ros_domain() as domain_id, tempfile.TemporaryDirectory(prefix="bench_e2e_") as tmp:
        home = Path(tmp)
        env = graph_env(domain_id, home)
        if graph_only:
            figures = run_kiosk(env, domain_id, home, graph_only)
        if demo_runs and "demo" in only:
            figures = {**run_demo(env, demo_runs), **figures}
    print(f"  {load_line()}; e2e bench took {time.monotonic() - t_start:.0f} s")
    return figures


def parse_only(text: str) -> tuple[str, ...]:
    """``--only``'s comma-separated scenario names, checked against :data:`SCENARIOS`."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown scenario(s) {', '.join(unknown) or '(none given)'}; "
            f"choose from {','.join(SCENARIOS)}")
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-demo", action="store_true", help="skip the demo runs")
    parser.add_argument("--only", type=parse_only, default=SCENARIOS, metavar="NAMES",
                        help="comma-separated scenarios to run, of " + ",".join(SCENARIOS)
                        + " (default all; sweep implies kiosk and kiosk10), e.g. "
                        "--only kiosk10,print")
    args = parser.parse_args(argv)
    with exit_codes("bench_e2e", BenchError, interrupted="the nodes were stopped"):
        figures = run(demo_runs=0 if args.no_demo else DEMO_RUNS, only=args.only)
    print_figures(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
