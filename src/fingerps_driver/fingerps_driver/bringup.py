"""bringup: the whole fingerps graph as separate processes, from one parameter file.

``ros2 run fingerps_driver bringup [--params FILE]`` starts driver_node, calib_node,
recon_node, recorder_node and scan_node, each with ``--ros-args --params-file FILE`` (a
standard ROS 2 parameter file: one section per node, ``/fingerps/<node>: ros__parameters:``).
The file chooses the rig: ``config/fingerps_sim.yaml`` (the default, the simulated rig) or
``config/fingerps_hardware.yaml`` (a serial LED board and a V4L2 camera).

Bad input stops bringup with exit code 2: the file is checked first (YAML, only the graph's
node names as sections, each with a ``ros__parameters`` mapping) and nothing is started if
it is wrong; a parameter a node does not have, or of the wrong type, makes that node exit at
once with one line naming the key, and bringup then stops the others.

Ctrl-C (SIGINT) or SIGTERM to bringup is passed on as one SIGTERM to every node (each runs
in its own session, so a terminal's Ctrl-C reaches only bringup; the nodes treat SIGTERM as
Ctrl-C, and a node still importing its modules ends quietly instead of with a
KeyboardInterrupt traceback): the driver switches the LEDs off and the recorder finalises its
bag. Exit code 0 when every node exited cleanly. Further signals (a second Ctrl-C, SIGINT to
the process group and SIGTERM from a supervisor) change nothing: each node gets one SIGTERM,
and ``bringup`` itself ignores SIGINT and SIGTERM from then until it exits (no traceback).

This lives in fingerps_driver beside the demo, which starts the same graph: bringup is the
user-facing command; a launch file for full ROS 2 installations is
``launch/fingerps.launch.py``.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml
from ament_index_python.packages import get_package_prefix, get_package_share_directory

from fingerps_driver.errors import BringupError
from fingerps_ros.command_line import EXIT_BAD_INPUT, CommandLineTool
from fingerps_ros.privacy import use_localhost_discovery

NAMESPACE = "/fingerps"


@dataclass(frozen=True)
class GraphNode:
    """One node of the graph: its name in the namespace and how to run it."""

    name: str
    package: str
    executable: str


GRAPH = (
    GraphNode("driver", "fingerps_driver", "driver_node"),
    GraphNode("calib", "fingerps_calib", "calib_node"),
    GraphNode("recon", "fingerps_recon", "recon_node"),
    GraphNode("recorder", "fingerps_recon", "recorder_node"),
    GraphNode("scan", "fingerps_recon", "scan_node"),
)


TOOL = CommandLineTool("bringup", bad_input=(BringupError,), error_prefix="[bringup] error: ")


def check_params_file(path: Path) -> dict:
    """Parse and check a parameter file's structure; return it. Raises ``BringupError``."""
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise BringupError(f"cannot read the parameter file {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise BringupError(f"the parameter file {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise BringupError(f"the parameter file {path} must map node names to sections")
    known = {f"{NAMESPACE}/{n.name}" for n in GRAPH} | {"/**"}
    for key, section in data.items():
        if key not in known:
            raise BringupError(
                f"{path}: unknown node {key!r}; the graph's nodes are "
                f"{', '.join(sorted(known))}")
        if not isinstance(section, dict) or set(section) != {"ros__parameters"} \
                or not isinstance(section["ros__parameters"], dict):
            raise BringupError(f"{path}: section {key!r} must hold exactly one mapping, "
                               "'ros__parameters'")
    return data


def default_params_file() -> Path:
    """The simulated rig's parameter file installed with fingerps_driver."""
    return Path(get_package_share_directory("fingerps_driver")) / "config" / "fingerps_sim.yaml"


def _executable(node: GraphNode) -> str:
    path = Path(get_package_prefix(node.package)) / "lib" / node.package / node.executable
    if not path.is_file():
        raise BringupError(f"{path} is missing: build the workspace (make build)")
    return str(path)


class Graph:
    """The node processes; ``stop()`` sends each one SIGTERM once and waits."""

    def __init__(self, params: Path, log_dir: Path | None) -> None:
        self.processes: list[tuple[GraphNode, subprocess.Popen]] = []
        self._logs = []
        commands = [(node, [_executable(node), "--ros-args", "--params-file", str(params)])
                    for node in GRAPH]
        for node, command in commands:
            output = None
            if log_dir is not None:
                output = open(log_dir / f"{node.executable}.log", "wb")  # closed in stop()
                self._logs.append(output)
            self.processes.append((node, subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=output,
                stderr=subprocess.STDOUT if output else None, start_new_session=True)))

    def exited(self) -> list[tuple[GraphNode, int]]:
        """Nodes that have exited, with their codes."""
        return [(node, proc.returncode) for node, proc in self.processes
                if proc.poll() is not None]

    def stop(self, timeout_s: float) -> dict[str, int]:
        """SIGTERM every running node, wait up to ``timeout_s``, SIGKILL what remains."""
        for _, proc in self.processes:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        codes = {}
        for node, proc in self.processes:
            try:
                codes[node.executable] = proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[node.executable] = proc.wait()
                print(f"[bringup] {node.executable} did not stop within {timeout_s:g} s; "
                      "killed", file=sys.stderr, flush=True)
        for log in self._logs:
            log.close()
        return codes


def run(params: Path, *, log_dir: Path | None, stop_timeout_s: float,
        ignore_signals_after: bool = False) -> int:
    """Start the graph and supervise it until a signal or a node's exit; return the code.

    SIGINT and SIGTERM are caught while it runs; afterwards the previous handlers are back,
    or, with ``ignore_signals_after`` (the command: the process is about to exit), both
    signals are ignored."""
    check_params_file(params)
    if log_dir is not None:
        log_dir.mkdir(parents=True, exist_ok=True)
    stopping = []

    def on_signal(signum: int, _frame: object) -> None:
        stopping.append(signum)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        graph = Graph(params, log_dir)
        print(f"[bringup] started {', '.join(n.executable for n in GRAPH)} with {params}; "
              "Ctrl-C stops them", flush=True)
        failed: list[tuple[GraphNode, int]] = []
        while not stopping and not failed:
            failed = graph.exited()
            time.sleep(0.1)
        if failed:
            node, code = failed[0]
            what = ("refused its start-up input (its error line names the key)"
                    if code == EXIT_BAD_INPUT else f"exited with code {code}")
            print(f"[bringup] {node.executable} {what}; stopping the others", file=sys.stderr,
                  flush=True)
        codes = graph.stop(stop_timeout_s)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_IGN if ignore_signals_after else handler)
    print(f"[bringup] stopped: {', '.join(f'{k} {v}' for k, v in codes.items())}", flush=True)
    if failed:
        return EXIT_BAD_INPUT if failed[0][1] == EXIT_BAD_INPUT else 1
    # -SIGTERM: a node stopped while still importing, before it had opened anything
    return 0 if all(code in (0, -signal.SIGTERM) for code in codes.values()) else 1


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--params", type=Path, default=None,
                        help="ROS 2 parameter file of the graph (default: the installed "
                             "config/fingerps_sim.yaml)")
    parser.add_argument("--log-dir", type=Path, default=None,
                        help="write each node's output to <dir>/<executable>.log instead of "
                             "this terminal")
    parser.add_argument("--stop-timeout", type=float, default=20.0,
                        help="seconds the nodes get to stop after Ctrl-C (default 20)")
    return parser


def _run_command(args: argparse.Namespace) -> int:
    use_localhost_discovery()  # the graph it starts talks to this machine only, by default
    return run(args.params or default_params_file(), log_dir=args.log_dir,
               stop_timeout_s=args.stop_timeout, ignore_signals_after=True)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_driver bringup``."""
    return TOOL.main(_parser(), _run_command, argv)


if __name__ == "__main__":
    raise SystemExit(main())
