"""driver_node as a real process: bursts over the pty serial path, tagged with the LED the
board actually lit; published on the topics (bad start-up input: test_driver_cameras.py)."""

from __future__ import annotations

import signal

import numpy as np
import pytest
from rclpy.node import Node

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_msgs.msg import TaggedFrame
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array
from fingerps_ros.time_conversion import time_nanoseconds

NS = "/" + topics.NAMESPACE


def test_burst_frames_are_tagged_with_the_led_that_lit_them(
        ros_node: Node, start_node, spin_until, call_service, driver_topics) -> None:
    driver = start_node("fingerps_driver", "driver_node")
    driver.wait_in_graph(ros_node, "driver", NS)
    bursts, frames, client = driver_topics
    spin_until(lambda: ros_node.count_publishers(f"{NS}/{topics.BURST}") >= 1
               and ros_node.count_publishers(f"{NS}/{topics.FRAMES}") >= 1,
               "the driver's publishers")

    response = call_service(client, CaptureBurst.Request(with_dark_frame=True))
    assert response.success, response.message
    burst = response.burst
    assert [f.led_index for f in burst.frames] == list(range(7))
    assert all(f.led_count == 7 and f.burst_id == burst.burst_id for f in burst.frames)
    assert burst.has_dark_frame and burst.dark_frame.led_index == TaggedFrame.LED_DARK
    assert burst.camera_info.k[0] > 0 and burst.camera_info.width == 659
    stamps = [time_nanoseconds(f.header.stamp) for f in burst.frames]
    assert stamps == sorted(stamps)

    # Each frame must look like the rig under its tagged LED and under no other.
    rig = SimulatedRig(RigConfig())
    references = np.stack([rig.noiseless(Scene.FINGER, [k]).ravel() for k in range(7)])
    references -= references.mean(axis=1, keepdims=True)
    for frame in burst.frames:
        image = image_to_array(frame.image).astype(np.float64).ravel()
        image -= image.mean()
        correlation = references @ image / (np.linalg.norm(references, axis=1)
                                            * np.linalg.norm(image))
        assert int(np.argmax(correlation)) == frame.led_index, correlation
    dark = image_to_array(burst.dark_frame.image)
    assert dark.mean() < 0.02 * 255

    # frames are sensor data (best effort): some may be dropped, the burst (reliable) not.
    spin_until(lambda: bursts and frames, "the burst and its frames on the topics")
    assert bursts[-1].burst_id == burst.burst_id
    assert all(f.burst_id == burst.burst_id for f in frames)

    # A capture for calibration is answered but not published.
    published = len(bursts)
    response = call_service(client, CaptureBurst.Request(response_only=True))
    assert response.success and len(response.burst.frames) == 7
    with pytest.raises(pytest.fail.Exception):
        spin_until(lambda: len(bursts) > published, "no burst", timeout=1.0)

    driver.send_signal(signal.SIGTERM)
    assert driver.wait() == 0
    assert "Traceback" not in driver.output


def test_diagnostics_say_whether_continuous_capture_keeps_the_rate(
        ros_node: Node, start_node, spin_until) -> None:
    import time

    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    driver = start_node("fingerps_driver", "driver_node", "--ros-args", "-p", "rate:=30.0")
    driver.wait_in_graph(ros_node, "driver", NS)
    statuses: list[tuple[float, DiagnosticStatus]] = []  # (time received, status)
    ros_node.create_subscription(
        DiagnosticArray, topics.DIAGNOSTICS,
        lambda m: statuses.extend((time.monotonic(), s) for s in m.status
                                  if s.name.endswith("driver: bursts")), 10)

    def values(status: DiagnosticStatus) -> dict[str, str]:
        return {kv.key: kv.value for kv in status.values}

    def judged_twice() -> bool:  # two verdicts on full 5 s windows, 5 s apart
        judged = [(t, s) for t, s in statuses if values(s).get("rate_achieved")]
        return bool(judged) and judged[-1][0] - judged[0][0] >= 5.0

    spin_until(judged_twice, "the driver's verdicts on its rate", timeout=40.0)
    judged = [(t, s) for t, s in statuses if values(s).get("rate_achieved")]
    (t0, first), (t1, last) = judged[0], judged[-1]
    # What the driver captured between the two verdicts, from its own burst counter.
    counted = (int(values(last)["bursts_ok"]) - int(values(first)["bursts_ok"])) / (t1 - t0)
    achieved = float(values(last)["rate_achieved"])
    assert values(last)["rate_requested"] == "30"
    assert achieved == pytest.approx(counted, rel=0.15), (achieved, counted)
    behind = achieved < 0.9 * 30
    assert (last.level == DiagnosticStatus.WARN) == behind, last
    assert ("bursts/s of the 30 asked for" in last.message) == behind
    print(f"\nasked 30 bursts/s: the driver reports {achieved} ({counted:.1f} counted)")
    driver.send_signal(signal.SIGINT)
    assert driver.wait() == 0
