"""Soak: the bringup graph at 5 bursts/s for 30 minutes (``make soak``; not in ``make bench``).

``bringup`` starts every node (driver_node on the simulated rig, calib_node, recon_node hk,
recorder_node, scan_node) from a parameter file written to a temporary folder: the installed
``config/fingerps_sim.yaml`` with the driver's ``rate`` 0, ``calibration_dir`` and the
recorder's ``bags_dir`` in the temporary folder. In a ROS domain of its own, as
bench_e2e.py's kiosk: the benchmark's node (bench_e2e.Observer) calibrates the flat field and
the lights through the services, puts the finger in front of the camera and sets the
driver's ``rate`` to 5 bursts/s; it receives every ``/fingerps/burst`` (stamp only) and
``/fingerps/points`` and matches clouds to bursts by header stamp, and reads ``/diagnostics``.

After a warm-up (the first cloud, then ``WARM_UP_S``), a window of ``--minutes`` (default 30)
is measured with bench_e2e.measure; the RSS (VmRSS in /proc/<pid>/status) of every node
process (bringup's children) is sampled every ``SAMPLE_EVERY_S``. Then bringup is stopped
(SIGINT; it stops the nodes, the recorder finishes its bag) and the bag's metadata.yaml read.

- ``soak.minutes``: length of the window;
- ``soak.bursts_published``: bursts the driver published in the window (stamp inside it, as
  the benchmark's subscriber saw them); ``soak.published_per_s`` the same per second;
- ``soak.clouds_received``: clouds of those bursts received;
- ``soak.bursts_lost``: bursts of the window never reconstructed (no cloud after a grace);
- ``soak.recon_dropped``: recon_node's ``bursts_dropped`` (/diagnostics) at the end, since
  its start (so the warm-up included); ``soak.recon_failed`` its ``bursts_failed``;
- ``soak.latency_ms_median``, ``soak.latency_ms_p95``: burst stamp -> cloud received;
- ``soak.rss_mb.<node>.start`` / ``.end``: after the warm-up, and just before stopping;
- ``soak.rss_growth_mb_per_h.<node>``: slope of a least-squares line through the samples;
- ``soak.bag_pieces``: MCAP pieces listed in the bag's metadata.yaml ``files``;
  ``soak.bag_gb``: the bag directory's size (10^9 bytes); ``soak.bag_messages``;
- ``soak.recorder_not_written``: messages the recorder subscribed to and did not write: the
  finished bag's count (metadata.yaml ``custom_data`` ``fingerps.not_written``), else its
  /diagnostics' ``not_written`` (left out if neither has one).

The recorder splits the bag at ``MAX_BAGFILE_SIZE`` and caps ``bags_dir`` at
``DISK_BUDGET_GB`` (once recorder_node has those parameters: ``RECORDER_SPLITTING``). If the
run would write more than ``DISK_BUDGET_GB`` with the outputs (``RECORD_MB_PER_S``), the
recorder runs with ``record_outputs:=false`` (said in the output; ``--record-outputs``
chooses).

The figures are merged into ``--out`` (bench/results.json): its ``soak.*`` names replaced,
the others kept. Alone: ``python bench/bench_soak.py --minutes 2``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from fingerps_driver.bringup import GRAPH, default_params_file
from fingerps_driver.demo import executable, stop_graph
from fingerps_driver.errors import DemoError

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # ros_domain
import bench_e2e
from bench_e2e import (
    BenchError,
    Observer,
    cpu_seconds_from_stat,
    graph_env,
    load_line,
    measure,
    own_cpu_seconds,
    wait_until,
)
from figures_report import exit_codes, print_figures
from ros_domain import own_ros_domain

DEFAULT_MINUTES = 30.0
RATE_HZ = bench_e2e.RATE_HZ    # 5 bursts/s, the kiosk's rate
WARM_UP_S = 60.0               # after the first cloud, before the start sample
SAMPLE_EVERY_S = 30.0          # RSS samples
PROGRESS_EVERY_S = 300.0       # a progress line
NODE_START_TIMEOUT_S = 30.0    # bringup's five children appear
BRINGUP_STOP_TIMEOUT_S = 60.0  # what bringup gives the nodes (the recorder finishes its bag)

# recorder_node's size/duration splitting and bags_dir cap. False leaves the
# three parameters out of the file (a recorder without them refuses unknown parameters).
RECORDER_SPLITTING = True
MAX_BAGFILE_SIZE = 256 * 1024 * 1024  # bytes, a new piece <session>_<n>.mcap beyond
MAX_BAGFILE_DURATION = 0              # seconds; 0 = never
DISK_BUDGET_GB = 20.0                 # most a soak may write; also bags_dir_limit_mb
RECORD_MB_PER_S = {True: 32.0, False: 9.0}  # bag at 5 bursts/s, with/without the outputs


# ---------------------------------------------------------------------------- processes
def _stat_fields(pid: int) -> list[str] | None:
    """/proc/<pid>/stat after the command name: [state, ppid, ...]; None if gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return text[text.rindex(")") + 2:].split()


def _children(ppid: int) -> list[int]:
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = _stat_fields(int(entry))
            if fields is not None and int(fields[1]) == ppid:
                pids.append(int(entry))
    return pids


def _cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except (FileNotFoundError, ProcessLookupError):
        return []


def rss_mb(pid: int) -> float:
    """VmRSS of a process, MB (2^20 bytes)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise BenchError(f"no VmRSS for pid {pid}")


class Bringup:
    """``bringup --params FILE`` and its node processes (by the graph's short names)."""

    def __init__(self, params: Path, home: Path, env: dict[str, str]) -> None:
        self.log_dir = home / "node_logs"
        self.log = home / "bringup.log"
        with open(self.log, "wb") as log:
            self.proc = subprocess.Popen(
                [executable("fingerps_driver", "bringup"), "--params", str(params),
                 "--log-dir", str(self.log_dir), "--stop-timeout", f"{BRINGUP_STOP_TIMEOUT_S:g}"],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                start_new_session=True)
        self.pids: dict[str, int] = {}

    def find_nodes(self) -> dict[str, int]:
        """Wait for bringup's children: the pid of each node by name."""
        executables = {node.executable: node.name for node in GRAPH}
        deadline = time.monotonic() + NODE_START_TIMEOUT_S
        while True:
            self._check_bringup()
            for pid in _children(self.proc.pid):
                for arg in _cmdline(pid):
                    name = executables.get(Path(arg).name)
                    if name is not None:
                        self.pids[name] = pid
            if len(self.pids) == len(GRAPH):
                return self.pids
            if time.monotonic() > deadline:
                raise BenchError(f"bringup started only {sorted(self.pids)} within "
                                 f"{NODE_START_TIMEOUT_S:.0f} s")
            time.sleep(0.2)

    def _check_bringup(self) -> None:
        if self.proc.poll() is not None:
            raise BenchError(f"bringup exited with {self.proc.returncode}")

    def check_running(self) -> None:
        """BenchError naming the node if a node process or bringup has exited."""
        for name, pid in self.pids.items():
            fields = _stat_fields(pid)
            if fields is None or fields[0] in ("Z", "X"):
                raise BenchError(f"{name} node (pid {pid}) died")
        self._check_bringup()

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds (user + system) each node process has used so far (0 if gone), and
        this process's as ``bench``; as bench_e2e's Graph.cpu_seconds."""
        used = {}
        for name, pid in self.pids.items():
            fields = _stat_fields(pid)
            used[name] = 0.0 if fields is None else cpu_seconds_from_stat(fields)
        used["bench"] = own_cpu_seconds()
        return used

    def rss(self) -> dict[str, float]:
        try:
            return {name: rss_mb(pid) for name, pid in self.pids.items()}
        except FileNotFoundError:
            self.check_running()
            raise

    def tails(self, lines: int = 12) -> str:
        parts = []
        for path in [self.log, *sorted(self.log_dir.glob("*.log"))]:
            if path.is_file():
                text = path.read_text(errors="replace").splitlines()[-lines:]
                parts.append(f"{path.name}:\n" + "\n".join(f"  | {t}" for t in text))
        return "\n".join(parts)

    def stop(self) -> int:
        """SIGINT to bringup (it stops every node) and wait; kill what is left."""
        code = stop_graph([self.proc], timeout=BRINGUP_STOP_TIMEOUT_S + 30.0)[0]
        for name, pid in self.pids.items():
            fields = _stat_fields(pid)
            if fields is not None and fields[0] not in ("Z", "X") and any(
                    Path(a).name.startswith(name) for a in _cmdline(pid)):
                print(f"bench_soak: {name} node (pid {pid}) outlived bringup; killed",
                      file=sys.stderr)
                os.kill(pid, signal.SIGKILL)
        return code


# ---------------------------------------------------------------------------- set-up
def record_outputs_for(minutes: float) -> bool:
    """Whether the recorder may record the outputs within the disk budget."""
    seconds = (minutes + 3.0) * 60.0  # calibration, warm-up and stopping included
    return RECORD_MB_PER_S[True] * seconds / 1e3 <= DISK_BUDGET_GB


def write_params(home: Path, record_outputs: bool) -> Path:
    """The simulated rig's bringup file, with the soak's changes, in ``home``."""
    params = yaml.safe_load(default_params_file().read_text())

    def section(node: str) -> dict:
        return params.setdefault(f"/fingerps/{node}", {}).setdefault("ros__parameters", {})

    section("driver")["rate"] = 0.0  # set to RATE_HZ after the calibration
    section("calib")["calibration_dir"] = str(home / "calibration")
    recorder = section("recorder")
    recorder["bags_dir"] = str(home / "bags")
    recorder["record_outputs"] = record_outputs
    if RECORDER_SPLITTING:
        recorder["max_bagfile_size"] = MAX_BAGFILE_SIZE
        recorder["max_bagfile_duration"] = MAX_BAGFILE_DURATION
        recorder["bags_dir_limit_mb"] = int(DISK_BUDGET_GB * 1000)
    path = home / "soak_params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return path


# ---------------------------------------------------------------------------- figures
def recorder_not_written(observer: Observer) -> tuple[str, int] | None:
    """(key, count) of the recorder's messages not written, from its /diagnostics."""
    with observer.seen.lock:
        statuses = {name: dict(values) for name, values in observer.seen.diagnostics.items()
                    if name.startswith("recorder")}
    for name, values in statuses.items():
        if values.get("not_written", "").isdigit():
            return f"{name} / not_written", int(values["not_written"])
    for wanted in ("not_written", "dropped", "lost"):
        for name, values in statuses.items():
            for key, value in values.items():
                if wanted in key and value.strip().isdigit():
                    return f"{name} / {key}", int(value)
    return None


def bag_figures(bags_dir: Path) -> tuple[dict[str, float], list[str]]:
    """Pieces, size and messages of the session bag(s) in ``bags_dir``."""
    sessions = sorted(p for p in bags_dir.iterdir() if p.is_dir()) if bags_dir.is_dir() else []
    if not sessions:
        raise BenchError(f"no bag in {bags_dir}")
    pieces = messages = 0
    size = 0
    not_written: int | None = None
    lines = []
    for session in sessions:
        meta_path = session / "metadata.yaml"
        if not meta_path.is_file():
            raise BenchError(f"the bag {session.name} has no metadata.yaml (not finished)")
        info = yaml.safe_load(meta_path.read_text())["rosbag2_bagfile_information"]
        files = [f["path"] for f in info.get("files") or []] or list(
            info.get("relative_file_paths") or [])
        missing = [f for f in files if not (session / f).is_file()]
        if missing:
            raise BenchError(f"the bag {session.name} lists missing pieces: {missing}")
        session_size = sum(p.stat().st_size for p in session.iterdir() if p.is_file())
        pieces += len(files)
        messages += int(info.get("message_count", 0))
        size += session_size
        lines.append(f"bag {session.name}: {len(files)} piece(s), {session_size / 1e9:.2f} GB, "
                     f"{info.get('message_count')} messages")
        # the recorder's final count of messages not written, by topic and reason
        custom = (info.get("custom_data") or {}).get("fingerps.not_written")
        if custom is not None:
            by_topic = json.loads(custom)
            not_written = (not_written or 0) + sum(
                sum(reasons.values()) for reasons in by_topic.values())
            lines.append(f"bag {session.name}: not written {by_topic or 'none'}")
    figures = {"soak.bag_pieces": float(pieces), "soak.bag_gb": size / 1e9,
               "soak.bag_messages": float(messages)}
    if not_written is not None:
        figures["soak.recorder_not_written"] = float(not_written)
    return figures, lines


def rss_figures(samples: list[tuple[float, dict[str, float]]]) -> dict[str, float]:
    figures = {}
    t = np.array([s[0] for s in samples])
    hours = (t - t[0]) / 3600.0
    for node in samples[0][1]:
        rss = np.array([s[1][node] for s in samples])
        figures[f"soak.rss_mb.{node}.start"] = float(rss[0])
        figures[f"soak.rss_mb.{node}.end"] = float(rss[-1])
        figures[f"soak.rss_growth_mb_per_h.{node}"] = (
            float(np.polyfit(hours, rss, 1)[0]) if len(samples) >= 2 else float("nan"))
    return figures


# ---------------------------------------------------------------------------- the soak
def soak(bringup: Bringup, observer: Observer, minutes: float,
         lines: list[str]) -> dict[str, float]:
    """Calibrate, warm up, measure the window with RSS samples; the figures before stopping."""
    t_cal = time.monotonic()
    observer.calibrate()
    lines.append(f"calibration: {time.monotonic() - t_cal:.1f} s")
    observer.set_driver("rate", RATE_HZ)
    t_rate = time.monotonic()
    wait_until(lambda: observer.clouds_since(t_rate), timeout=bench_e2e.FIRST_CLOUD_TIMEOUT_S,
               what="the first point cloud", graph=bringup)
    lines.append(f"first cloud {observer.clouds_since(t_rate)[0] - t_rate:.1f} s after the "
                 f"rate was set; warm-up {WARM_UP_S:.0f} s")
    wait_until(lambda: time.monotonic() - t_rate > WARM_UP_S, timeout=WARM_UP_S + 5.0,
               what="the warm-up", graph=bringup)

    samples = [(time.monotonic(), bringup.rss())]
    t_start = samples[0][0]
    last_progress = [t_start]

    def tick() -> None:
        now = time.monotonic()
        if now - samples[-1][0] >= SAMPLE_EVERY_S:
            samples.append((now, bringup.rss()))
        if now - last_progress[0] >= PROGRESS_EVERY_S:
            last_progress[0] = now
            rss = ", ".join(f"{k} {v:.0f}" for k, v in samples[-1][1].items())
            counts = observer.recon_counts()
            print(f"  soak: {(now - t_start) / 60:.1f}/{minutes:g} min; recon done "
                  f"{counts.get('done')}, dropped {counts.get('dropped')}; RSS MB: {rss}",
                  flush=True)

    window = measure(observer, bringup, RATE_HZ, minutes * 60.0, tick=tick)
    lines.append(window.line())
    samples.append((time.monotonic(), bringup.rss()))  # just before stopping
    counts = observer.recon_counts()
    lat = window.latency_ms
    figures = {
        "soak.minutes": window.seconds / 60.0,
        "soak.bursts_published": float(window.published),
        "soak.published_per_s": window.published_per_s,
        "soak.clouds_received": float(window.published - window.lost),
        "soak.bursts_lost": float(window.lost),
        "soak.recon_dropped": float(counts.get("dropped", float("nan"))),
        "soak.recon_failed": float(counts.get("failed", float("nan"))),
        "soak.latency_ms_median": float(np.median(lat)) if lat else float("nan"),
        "soak.latency_ms_p95": float(np.percentile(lat, 95)) if lat else float("nan"),
        **rss_figures(samples),
    }
    not_written = recorder_not_written(observer)
    if not_written is None:
        lines.append("the recorder's /diagnostics give no count of messages not written")
    else:
        lines.append(f"recorder not written: {not_written[1]} ({not_written[0]})")
        figures["soak.recorder_not_written"] = float(not_written[1])
    lines.append(f"RSS samples (MB, every ~{SAMPLE_EVERY_S:.0f} s): " + "; ".join(
        f"{node} " + " ".join(f"{s[1][node]:.0f}" for s in samples) for node in samples[0][1]))
    return figures


def run(minutes: float = DEFAULT_MINUTES, record_outputs: bool | None = None) -> dict[str, float]:
    """The soak's figures; ``record_outputs`` None: as the disk budget allows."""
    t_start = time.monotonic()
    lines: list[str] = []
    with own_ros_domain() as domain_id, \
            tempfile.TemporaryDirectory(prefix="bench_soak_") as tmp:
        home = Path(tmp)
        if record_outputs is None:
            record_outputs = record_outputs_for(minutes)
        need_gb = RECORD_MB_PER_S[record_outputs] * (minutes + 3.0) * 60.0 / 1e3
        free_gb = shutil.disk_usage(home).free / 1e9
        if need_gb > 0.9 * free_gb:
            raise BenchError(f"the bag needs about {need_gb:.0f} GB; {free_gb:.0f} GB free "
                             f"in {home.parent}")
        print(f"  soak: {minutes:g} min at {RATE_HZ:g} bursts/s; recorder "
              + ("with the outputs" if record_outputs else
                 "with record_outputs:=false" + (
                     f" (with them the run would exceed {DISK_BUDGET_GB:g} GB)"
                     if not record_outputs_for(minutes) else ""))
              + (f", pieces of {MAX_BAGFILE_SIZE / 2**20:.0f} MiB, bags_dir cap "
                 f"{DISK_BUDGET_GB:g} GB" if RECORDER_SPLITTING else
                 ", no splitting (RECORDER_SPLITTING is off)")
              + f"; about {need_gb:.1f} GB of bag", flush=True)
        env = graph_env(domain_id, home)
        bringup = Bringup(write_params(home, record_outputs), home, env)
        observer = None
        code = None
        try:
            bringup.find_nodes()
            lines.append("nodes: " + ", ".join(f"{k} pid {v}" for k, v in bringup.pids.items()))
            observer = Observer(domain_id, name="bench_soak")
            figures = soak(bringup, observer, minutes, lines)
        except (BenchError, DemoError) as exc:
            time.sleep(1.0)  # bringup's line on a node's exit
            raise BenchError(f"{exc}\n{bringup.tails()}") from None
        finally:
            if observer is not None:
                observer.close()
            t_stop = time.monotonic()
            code = bringup.stop()
            lines.append(f"bringup stopped in {time.monotonic() - t_stop:.1f} s, exit code "
                         f"{code}")
            for line in lines:
                print(f"  soak: {line}")
        if code != 0:
            raise BenchError(f"bringup exited with {code} (a node did not stop cleanly)\n"
                             f"{bringup.tails()}")
        bag, bag_lines = bag_figures(home / "bags")
        for line in bag_lines:
            print(f"  soak: {line}")
        figures.update(bag)
    print(f"  {load_line()}; soak took {(time.monotonic() - t_start) / 60:.1f} min")
    return figures


def merge_results(path: Path, figures: dict[str, float]) -> None:
    """Replace the ``soak.*`` names of ``path`` (a flat JSON object) with ``figures``."""
    results = json.loads(path.read_text()) if path.is_file() else {}
    results = {k: v for k, v in results.items() if not k.startswith("soak.")}
    results.update(figures)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=DEFAULT_MINUTES,
                        help=f"length of the measured window (default {DEFAULT_MINUTES:g})")
    parser.add_argument("--record-outputs", choices=("auto", "true", "false"), default="auto",
                        help="record the reconstruction outputs too (default auto: if the "
                             f"bag stays within {DISK_BUDGET_GB:g} GB)")
    parser.add_argument("--out", type=Path, default=None,
                        help="merge the soak.* figures into this results.json")
    args = parser.parse_args(argv)
    if args.minutes <= 0:
        parser.error("--minutes must be positive")
    with exit_codes("bench_soak", BenchError, interrupted="the graph was stopped"):
        figures = run(args.minutes, None if args.record_outputs == "auto"
                      else args.record_outputs == "true")
    print_figures(figures)
    if args.out is not None:
        merge_results(args.out, figures)
        print(f"merged {len(figures)} soak.* figures into {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
