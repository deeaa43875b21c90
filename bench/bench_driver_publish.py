"""What publishing adds to a burst: driver_node on the simulated rig (659x493 mono8), as a
separate process, with a subscriber to every image topic in this process.

30 bursts are requested back to back through the capture_burst service (after 2 warm-up
bursts). The node times its own publishing path per burst - building the 7 TaggedFrames,
Images, CameraInfo and the Burst message and publishing them - and reports the median and
maximum over its recent bursts in its diagnostics (``publish_ms_median``,
``publish_ms_max``; the warm-up bursts are included). driver.service_ms.median is the
service round trip seen from here (capture + publish + the response carrying the burst).
Target: publishing adds <= 20 ms per burst.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import CameraInfo, Image

from fingerps_driver.demo import executable
from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import qos, topics

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # ros_domain
from graph_harness import bench_node
from ros_domain import domain_env, own_ros_domain

BURSTS = 30
WARM_UP = 2
NS = "/" + topics.NAMESPACE


def run() -> dict[str, float]:
    with own_ros_domain() as domain:
        return _run_in(domain)


def _run_in(domain: int) -> dict[str, float]:
    env = domain_env(domain)
    exe = executable("fingerps_driver", "driver_node")
    with tempfile.TemporaryFile() as log:
        driver = subprocess.Popen([exe], env=env, stdout=log, stderr=subprocess.STDOUT,
                                  start_new_session=True)
        try:
            return _measure(domain, driver)
        except Exception:
            log.seek(0)
            print(log.read().decode(errors="replace"))
            raise
        finally:
            driver.terminate()
            driver.wait(timeout=20)


def _measure(domain: int, driver: subprocess.Popen) -> dict[str, float]:
    with bench_node("fingerps_bench_publish", domain, watched=driver,
                    watched_name="driver_node", period=0.02) as bench:
        node, spin_until = bench.node, bench.spin_until
        counts = {"burst": 0, "frames": 0, "images": 0}
        diagnostics: list[dict[str, str]] = []

        def count(name: str) -> Callable[[object], None]:
            return lambda _msg: counts.__setitem__(name, counts[name] + 1)

        def on_diag(array: DiagnosticArray) -> None:
            for status in array.status:
                if status.name.endswith(": bursts"):
                    diagnostics.append({kv.key: kv.value for kv in status.values})

        node.create_subscription(Burst, f"{NS}/{topics.BURST}", count("burst"), qos.BURST_QOS)
        node.create_subscription(TaggedFrame, f"{NS}/{topics.FRAMES}", count("frames"),
                                 qos.SENSOR_QOS)
        node.create_subscription(Image, f"{NS}/{topics.IMAGE_RAW}", count("images"),
                                 qos.SENSOR_QOS)
        node.create_subscription(CameraInfo, f"{NS}/{topics.CAMERA_INFO}", lambda _m: None,
                                 qos.SENSOR_QOS)
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, 10)
        client = node.create_client(CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}")
        spin_until(client.service_is_ready, "the capture_burst service", 60.0)
        spin_until(lambda: node.count_publishers(f"{NS}/{topics.BURST}") >= 1
                   and node.count_publishers(f"{NS}/{topics.FRAMES}") >= 1,
                   "the driver's publishers", 30.0)
        round_trips = []
        for i in range(WARM_UP + BURSTS):
            start = time.perf_counter()
            future = client.call_async(CaptureBurst.Request())
            spin_until(future.done, "a burst", 30.0)
            if not future.result().success:
                raise RuntimeError(future.result().message)
            if i >= WARM_UP:
                round_trips.append((time.perf_counter() - start) * 1e3)
        total = WARM_UP + BURSTS
        spin_until(lambda: counts["burst"] >= total, "every burst on its topic", 10.0)
        spin_until(lambda: diagnostics and int(diagnostics[-1]["timing_window"]) >= total,
                   "the driver's diagnostics of every burst", 5.0)
        last = diagnostics[-1]
        print(f"  received {counts['burst']} bursts, {counts['frames']} tagged frames, "
              f"{counts['images']} images; in-node burst median {last['burst_ms_median']} ms")
        return {
            "driver.publish_ms.median": float(last["publish_ms_median"]),
            "driver.publish_ms.max": float(last["publish_ms_max"]),
            "driver.service_ms.median": statistics.median(round_trips),
        }


if __name__ == "__main__":
    for name, value in run().items():
        print(f"{name:<28} {value:10.3f}")
