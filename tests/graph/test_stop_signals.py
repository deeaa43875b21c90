"""Stopping is idempotent and signal-safe: real node processes get two stop signals.

Under ``ros2 launch`` run non-interactively, launch forwards SIGINT to each node and the
process group gets one too, so every node sees SIGINT twice; a supervisor may follow with
SIGTERM. In a running graph (the driver publishing bursts at 10/s, the recorder recording
them) every node gets SIGINT twice, SIGINT then SIGTERM, SIGTERM then SIGINT, back to back
and 50 ms apart; and each node kind gets a signal every 10 ms until it has exited.
Every node must exit 0 without a traceback, and the recorder must leave a complete bag
(metadata.yaml, an MCAP readable to its footer by the independent ``mcap`` library).
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from rclpy.node import Node

from fingerps_msgs.msg import Burst
from fingerps_ros import qos, topics

NS = "/" + topics.NAMESPACE
NODES = {
    "driver": ("fingerps_driver", "driver_node", ()),
    "calib": ("fingerps_calib", "calib_node", ("calibration_dir",)),
    "recon": ("fingerps_recon", "recon_node", ()),
    "scan": ("fingerps_recon", "scan_node", ()),
    "recorder": ("fingerps_recon", "recorder_node", ("bags_dir",)),
}
PAIRS = {
    "SIGINT-SIGINT": (signal.SIGINT, signal.SIGINT),
    "SIGINT-SIGTERM": (signal.SIGINT, signal.SIGTERM),
    "SIGTERM-SIGINT": (signal.SIGTERM, signal.SIGINT),
}
# back to back (launch's SIGINT and the process group's) and 50 ms apart (while stopping)
GAPS_S = (0.0, 0.05)
CHUNK_BYTES = 512 * 1024 * 1024
RECORDED_BURSTS = 30  # at 10/s: 3 s of bursts in the recorder's open chunk


def _args(paths: tuple[str, ...], tmp_path: Path) -> list[str]:
    args = ["--ros-args"]
    for name in paths:
        args += ["-p", f"{name}:={tmp_path / name}"]
    if "bags_dir" in paths:
        # One large chunk written only at the end: finishing the bag compresses a few
        # seconds of bursts, long enough for a second signal to arrive inside finish().
        args += ["-p", "session_name:=stop_session", "-p", "flush_period:=0.0",
                 "-p", f"chunk_size:={CHUNK_BYTES}"]
    return args


def _assert_clean_exit(proc, code: int) -> None:
    output = proc.output
    assert code == 0, output
    assert "Traceback" not in output, output
    assert "KeyboardInterrupt" not in output, output


def _assert_complete_bag(bag_dir: Path) -> int:
    """metadata.yaml present and consistent, the MCAP readable to its footer; message count."""
    metadata = yaml.safe_load((bag_dir / "metadata.yaml").read_text())
    info = metadata["rosbag2_bagfile_information"]
    (mcap_path,) = sorted(bag_dir.glob("*.mcap"))
    with open(mcap_path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()  # reads the footer and the summary section
        assert summary is not None and summary.statistics is not None
        messages = sum(1 for _ in reader.iter_messages())
    assert messages == summary.statistics.message_count == info["message_count"]
    return messages


def _send(procs, first: int, second: int, gap_s: float) -> None:
    for proc in procs:
        proc.send_signal(first)
    if gap_s:
        time.sleep(gap_s)
    for proc in procs:
        proc.send_signal(second)


def _graph(ros_node: Node, start_node, spin_until, tmp_path: Path) -> dict:
    """The five nodes as separate processes, the driver publishing bursts at 10/s and the
    recorder with ``RECORDED_BURSTS`` of them received."""
    procs = {}
    for kind, (package, executable, paths) in NODES.items():
        extra = ["-p", "rate:=10.0"] if kind == "driver" else []
        procs[kind] = start_node(package, executable, *_args(paths, tmp_path), *extra)
    for kind, proc in procs.items():
        proc.wait_in_graph(ros_node, kind, NS, timeout=60.0)
    seen = []
    ros_node.create_subscription(Burst, f"{NS}/{topics.BURST}", seen.append, qos.BURST_QOS)
    spin_until(lambda: len(seen) >= RECORDED_BURSTS, f"{RECORDED_BURSTS} bursts",
               timeout=60.0)
    return procs


@pytest.mark.parametrize("gap_s", GAPS_S, ids=lambda g: f"{g * 1000:.0f}ms")
@pytest.mark.parametrize("pair", list(PAIRS), ids=list(PAIRS))
def test_every_node_stops_cleanly_on_a_double_signal(
        pair: str, gap_s: float, ros_node: Node, start_node, spin_until,
        tmp_path: Path) -> None:
    """As under ros2 launch: every node of a running graph gets two signals."""
    procs = _graph(ros_node, start_node, spin_until, tmp_path)
    _send(procs.values(), *PAIRS[pair], gap_s)
    for proc in procs.values():
        _assert_clean_exit(proc, proc.wait(timeout=60.0))
    assert _assert_complete_bag(tmp_path / "bags_dir" / "stop_session") > 1


@pytest.mark.parametrize("kind", list(NODES))
def test_signals_repeated_while_stopping_are_ignored_until_resources_are_closed(
        kind: str, ros_node: Node, start_node, spin_until, tmp_path: Path) -> None:
    """SIGINT, then SIGTERM and SIGINT in turn every 10 ms until the node has exited."""
    proc = _graph(ros_node, start_node, spin_until, tmp_path)[kind]
    sent = proc.signal_until_exit(timeout=60.0)
    _assert_clean_exit(proc, proc.wait(timeout=10.0))
    assert sent > 2
    if kind == "recorder":
        assert _assert_complete_bag(tmp_path / "bags_dir" / "stop_session") > 1
