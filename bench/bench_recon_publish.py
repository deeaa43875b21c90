"""What converting and publishing recon_node's outputs costs, output by output, per burst.

Usage (tools/ros_env.sh sourced): ``python bench/bench_recon_publish.py [--repeats N]``.

One simulated 659x493 burst of 7 (``bench_recon_speed._burst``) is reconstructed once with
``fingerps_recon.photometric.pipeline.reconstruct`` (model lambert, as ``pipeline(model)`` in
bench_recon_speed); its result is then converted and published N times (default 21, at least
15, after one warm-up round) as ``recon_node._reconstruct`` does, in its order:

- normals: ``ps_to_optical(normals_ps, dtype=np.float32)`` + ``array_to_image`` 32FC3
  (3.9 MB);
- normal_map: ``normal_map_rgb`` of the enhanced normals + ``array_to_image`` rgb8 (1 MB);
- depth, albedo: ``array_to_image`` 32FC1 (1.3 MB each);
- points: ``points_to_cloud`` (x y z intensity float32, ~170 000 points, 2.8 MB).

Every message goes through ``publisher.publish`` of a real rclpy node on the topics recon
publishes (``/fingerps/...``, ``qos.OUTPUT_QOS``), to one subscriber in another process
subscribed to the five topics (raw, so it takes the serialised bytes without decoding them
in Python). After each round the benchmark waits until that subscriber has taken the
round's five messages, so a round's publishing never competes with the previous round's
delivery; ``total.delivered`` is the time from the round's first conversion to that
acknowledgement. The run has a ROS domain of its own (locked as tests/conftest.py
does) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``.

``run()`` returns medians (ms) over the rounds: ``recon.publish_ms.<output>.convert`` and
``.publish``, ``recon.publish_ms.total.convert`` / ``.publish`` / ``.delivered`` (medians of
the per-round sums), and ``recon.intake_ms.burst_decode``: the burst intake of recon_node,
seven mono8 659x493 images as a subscriber receives them decoded into one (7, H, W) array
(``images_to_array``).

Measured on the 2-core machine (others' work keeping its load average at 2.5-4), medians in
ms of convert / publish, before -> after the copies were removed (same runs, alternated):
normals 2.6 / 1.1-2.0 -> 0.8 / 1.0-1.7; normal_map 2.9 / 0.4-0.7 -> 0.85 / 0.3; depth and
albedo 0.1 / 0.25-0.3 each (unchanged); points 0.7 / 0.6 -> 0.4 / 0.6; all five converted
6.6-8.1 -> 2.1-2.3; burst intake 0.13 -> 0.06. publish() itself is rclpy's copy into the C
message, the CDR serialisation and Fast DDS's hand-over (~0.25 ms/MB).

Delivery dominates: with rmw_fastrtps_cpp's default transports (shared memory with 512 KB
segments, UDP), a round of these five messages (~10 MB) reached the other process in ~60 ms
on an idle machine but in ~3000 ms (median) at load 2.5-4: fragments are dropped and
recovered only at the writer's next heartbeat (Fast DDS's default period is 3 s; a profile
with a 100 ms period gives ~130 ms). A Fast DDS profile with a 32 MB shared-memory segment
(FASTRTPS_DEFAULT_PROFILES_FILE) gives 14-17 ms under the same load; UDP only, a 4 MB
segment or FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA still stall. So every fingerps node uses
``fingerps_recon/config/fastdds_large_data.xml`` (a 32 MB segment and a 100 ms heartbeat)
unless the user has a profile of their own (``node_runner.use_large_data_profile``), and so
does this benchmark's publisher; its subscriber keeps Fast DDS's defaults, as a viewer would.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # ros_domain
from figures_report import parse_repeats
from graph_harness import bench_node
from ros_domain import domain_env, own_ros_domain

RUNS = 21
MIN_RUNS = 15
OUTPUTS = ("normals", "normal_map", "depth", "albedo", "points")
ACK_TOPIC = "bench_recon_publish_ack"
START_TIMEOUT_S = 60.0
ROUND_TIMEOUT_S = 20.0


# ------------------------------------------------------------------ the subscriber process
def _subscribe() -> int:
    """The other process: raw subscriptions to recon's five outputs; after every message
    it publishes how many it has taken so far on ``ACK_TOPIC``; prints the counts as JSON
    on SIGINT/SIGTERM."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from sensor_msgs.msg import Image, PointCloud2
    from std_msgs.msg import UInt32

    from fingerps_ros import qos, topics

    rclpy.init()
    node = rclpy.create_node("bench_recon_publish_sink", namespace=topics.NAMESPACE)
    counts = dict.fromkeys(OUTPUTS, 0)
    sizes = dict.fromkeys(OUTPUTS, 0)
    ack = node.create_publisher(UInt32, ACK_TOPIC, 10)

    def take(name: str) -> Callable[[bytes], None]:
        def on_message(raw: bytes) -> None:
            counts[name] += 1
            sizes[name] = len(raw)
            ack.publish(UInt32(data=sum(counts.values())))
        return on_message

    types = {"normals": Image, "normal_map": Image, "depth": Image, "albedo": Image,
             "points": PointCloud2}
    names = {"normals": topics.NORMALS, "normal_map": topics.NORMAL_MAP,
             "depth": topics.DEPTH, "albedo": topics.ALBEDO, "points": topics.POINTS}
    for name in OUTPUTS:
        node.create_subscription(types[name], names[name], take(name), qos.OUTPUT_QOS,
                                 raw=True)
    signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    print(json.dumps({"counts": counts, "bytes": sizes}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# ------------------------------------------------------------------ the measuring process


def _result() -> object:
    """The Reconstruction of one simulated burst, as recon_node would publish it."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_recon_speed import _burst

    from fingerps_driver.simulation import RigConfig, SimulatedRig
    from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions, reconstruct

    rig = SimulatedRig(RigConfig())
    burst = _burst(rig)
    return reconstruct(
        burst.images, lights_ps=burst.lights_ps, camera_matrix=burst.camera_matrix,
        full_scale=burst.full_scale, intensities=burst.intensities,
        portions=burst.portions, led_positions_optical=rig.led_positions_optical,
        options=ReconstructionOptions(model=Model.LAMBERT, enhance=True))


def _conversions(result: object, header: object) -> dict[str, Callable[[], object]]:
    """Array -> message, per output, as recon_node._reconstruct does it."""
    from fingerps_recon.photometric.frames import ps_to_optical
    from fingerps_recon.photometric.normal_map import normal_map_rgb
    from fingerps_ros.image_conversion import array_to_image
    from fingerps_ros.point_cloud_conversion import points_to_cloud

    r = result
    shown = r.enhanced_ps if r.enhanced_ps is not None else r.normals_ps
    return {
        "normals": lambda: array_to_image(ps_to_optical(r.normals_ps, dtype=np.float32),
                                          encoding="32FC3", header=header),
        "normal_map": lambda: array_to_image(normal_map_rgb(shown, mask=r.mask),
                                             encoding="rgb8", header=header),
        "depth": lambda: array_to_image(r.depth_m, encoding="32FC1", header=header),
        "albedo": lambda: array_to_image(r.albedo, encoding="32FC1", header=header),
        "points": lambda: points_to_cloud(r.points_optical, r.point_albedo, header=header),
    }


def _intake(result: object, repeats: int) -> list[float]:
    """Times (ms) of decoding a burst's seven mono8 images, received through CDR, into one
    (7, H, W) array as recon_node does."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image

    from fingerps_ros.image_conversion import array_to_image, images_to_array

    rng = np.random.default_rng(7)
    h, w = result.mask.shape
    sent = [array_to_image(rng.integers(0, 256, (h, w), dtype=np.uint8), encoding="mono8")
            for _ in range(7)]
    received = [deserialize_message(serialize_message(m), Image) for m in sent]

    def decode() -> np.ndarray:
        return images_to_array(received)

    decode()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        decode()
        times.append((time.perf_counter() - start) * 1e3)
    return times


def measure(repeats: int = RUNS) -> dict[str, list[float]]:
    """Per-round times (ms): ``<output>.convert``, ``<output>.publish``, ``total.*``, and
    ``intake``; see the module docstring."""
    if repeats < MIN_RUNS:
        raise ValueError(f"repeats must be >= {MIN_RUNS}, got {repeats}")
    result = _result()
    times = {"intake": _intake(result, repeats)}
    with own_ros_domain() as domain, tempfile.TemporaryFile("w+") as log:
        env = domain_env(domain, PYTHONUNBUFFERED="1")
        saved = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # read by rclpy.init
        sink = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--subscribe"],
                                env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            times.update(_publish_rounds(result, domain, repeats, sink))
        finally:
            summary = _stop(sink, log)
            if saved is None:
                os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
            else:
                os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = saved
    received = summary.get("counts", {})
    if any(received.get(name) != repeats + 1 for name in OUTPUTS):
        raise RuntimeError(f"the subscriber took {received}, expected {repeats + 1} of each")
    return times


def _publish_rounds(result: object, domain: int, repeats: int,
                    sink: subprocess.Popen) -> dict[str, list[float]]:
    from sensor_msgs.msg import Image, PointCloud2
    from std_msgs.msg import Header, UInt32

    from fingerps_ros import qos, topics
    from fingerps_ros.node_runner import use_large_data_profile

    use_large_data_profile()  # as every fingerps node does (the subscriber keeps the default)
    with bench_node("bench_recon_publish", domain, namespace=topics.NAMESPACE, watched=sink,
                    watched_name="the subscriber", period=0.005) as bench:
        node, spin_until = bench.node, bench.spin_until
        names = {"normals": topics.NORMALS, "normal_map": topics.NORMAL_MAP,
                 "depth": topics.DEPTH, "albedo": topics.ALBEDO, "points": topics.POINTS}
        publishers = {
            name: node.create_publisher(PointCloud2 if name == "points" else Image,
                                        names[name], qos.OUTPUT_QOS)
            for name in OUTPUTS}
        taken = [0]
        node.create_subscription(UInt32, ACK_TOPIC,
                                 lambda msg: taken.__setitem__(0, msg.data), 10)

        spin_until(lambda: all(p.get_subscription_count() >= 1 for p in publishers.values())
                   and node.count_publishers(f"/{topics.NAMESPACE}/{ACK_TOPIC}") >= 1,
                   "the subscriber process", START_TIMEOUT_S)
        time.sleep(0.5)  # let discovery settle (both directions)
        header = Header(frame_id="fingerps_camera_optical_frame")
        header.stamp = node.get_clock().now().to_msg()
        convert = _conversions(result, header)
        times: dict[str, list[float]] = {}
        for round_index in range(repeats + 1):
            lap: dict[str, float] = {}
            start = time.perf_counter()
            for name in OUTPUTS:
                t0 = time.perf_counter()
                msg = convert[name]()
                t1 = time.perf_counter()
                publishers[name].publish(msg)
                t2 = time.perf_counter()
                lap[f"{name}.convert"] = (t1 - t0) * 1e3
                lap[f"{name}.publish"] = (t2 - t1) * 1e3
                del msg
            expected = (round_index + 1) * len(OUTPUTS)
            spin_until(lambda e=expected: taken[0] >= e, "the round's messages",
                       ROUND_TIMEOUT_S)
            lap["total.delivered"] = (time.perf_counter() - start) * 1e3
            lap["total.convert"] = sum(lap[f"{n}.convert"] for n in OUTPUTS)
            lap["total.publish"] = sum(lap[f"{n}.publish"] for n in OUTPUTS)
            if round_index > 0:  # round 0 warms up
                for key, value in lap.items():
                    times.setdefault(key, []).append(value)
        return times


def _stop(sink: subprocess.Popen, log: TextIO) -> dict:
    """Stop the subscriber and return the JSON summary it printed ({} if none)."""
    if sink.poll() is None:
        sink.send_signal(signal.SIGINT)
        try:
            sink.wait(timeout=20)
        except subprocess.TimeoutExpired:
            sink.kill()
            sink.wait(timeout=20)
    log.seek(0)
    text = log.read()
    for line in reversed(text.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    print(text)
    return {}


def run(repeats: int = RUNS) -> dict[str, float]:
    """Medians (ms): ``recon.publish_ms.<output>.convert|publish``, ``recon.publish_ms.total.
    convert|publish|delivered`` and ``recon.intake_ms.burst_decode``."""
    times = measure(repeats)
    figures = {f"recon.publish_ms.{key}": statistics.median(values)
               for key, values in times.items() if key != "intake"}
    figures["recon.intake_ms.burst_decode"] = statistics.median(times["intake"])
    return figures


def _print(times: dict[str, list[float]], repeats: int) -> None:
    load = os.getloadavg()[0]
    print(f"recon publishing: 659x493 outputs of one burst, {repeats} rounds, "
          f"{os.cpu_count()} cores, load average {load:.2f}")
    print(f"  {'output':<12} {'convert':>9} {'publish':>9}   (median ms; IQR of both)")
    for name in [*OUTPUTS, "total"]:
        c, p = times[f"{name}.convert"], times[f"{name}.publish"]
        cq, pq = np.percentile(c, [25, 75]), np.percentile(p, [25, 75])
        print(f"  {name:<12} {statistics.median(c):9.2f} {statistics.median(p):9.2f}   "
              f"{cq[0]:.2f}-{cq[1]:.2f}  {pq[0]:.2f}-{pq[1]:.2f}")
    print(f"  round, first conversion -> the subscriber took all five: "
          f"{statistics.median(times['total.delivered']):.2f} ms median")
    print(f"  burst intake, 7 mono8 images decoded into (7, H, W): "
          f"{statistics.median(times['intake']):.3f} ms median")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--subscribe", action="store_true", help=argparse.SUPPRESS)
    args = parse_repeats(parser, argv, runs=RUNS, min_runs=MIN_RUNS, what="rounds")
    if args.subscribe:
        return _subscribe()
    _print(measure(args.repeats), args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
