"""bag_replay as a real process feeding a real recon_node: the bag is written here with
SessionBagWriter from messages of the simulated rig (a LightCalibration and two Bursts one
second apart), played at its recorded timing, and recon's normals are compared with
the pipeline run directly on the bursts read back from the bag, in their order (the HK fit
of A of each burst after the first starts from the previous burst's A, as in the node).

Equality: bitwise (``np.array_equal``) - the node runs the same function on the same arrays
in the same order on the same machine, so nothing but the transport differs.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from fingerps_driver.simulation import Scene
from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical
from fingerps_recon.photometric.pipeline import (
    Model,
    ReconstructionOptions,
    prepare_calibration,
    reconstruct_prepared,
)
from fingerps_recon.sessions.bag_reader import SessionBagReader
from fingerps_recon.sessions.message_definition import MessageDefinition, load_message_definition
from fingerps_recon.sessions.rosbag2_qos import QosProfileFields, qos_profiles_yaml
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import image_to_array

NS = "/" + topics.NAMESPACE
BURST_TOPIC = f"{NS}/{topics.BURST}"
LIGHTS_TOPIC = f"{NS}/{topics.LIGHT_CALIBRATION}"
T0 = 1_700_000_000_000_000_000


def _burst(rig_messages, burst_id: int) -> Burst:
    rig = rig_messages.rig
    images = rig.render_burst(Scene.FINGER, seed=50 * burst_id)
    return rig_messages.burst(images, burst_id, nanosec=0)


@pytest.fixture(scope="module")
def session_bag(tmp_path_factory: pytest.TempPathFactory, rig_messages) -> Path:
    path = tmp_path_factory.mktemp("replay") / "session"
    with SessionBagWriter(path) as bag:
        bag.add_topic(LIGHTS_TOPIC, "fingerps_msgs/msg/LightCalibration",
                      offered_qos_yaml=qos_profiles_yaml(QosProfileFields.from_profile(
                          qos.CALIBRATION_QOS)))
        bag.add_topic(BURST_TOPIC, "fingerps_msgs/msg/Burst",
                      offered_qos_yaml=qos_profiles_yaml(QosProfileFields.from_profile(
                          qos.BURST_QOS)))
        lights = rig_messages.light_calibration("replay_test")
        bag.write(LIGHTS_TOPIC, serialize_message(lights), log_time_ns=T0, publish_time_ns=T0)
        for i in (1, 2):
            t = T0 + i * 1_000_000_000
            bag.write(BURST_TOPIC, serialize_message(_burst(rig_messages, i)), log_time_ns=t,
                      publish_time_ns=t)
    return path


def _direct_normals(lights: LightCalibration, burst: Burst,
                    initial_scale: float | None) -> tuple[np.ndarray, float | None]:
    """recon_node's computation, without ROS (its default parameters), the HK fit of A
    started from ``initial_scale`` (the previous burst's A): the normals and the new A."""
    frames = sorted(burst.frames, key=lambda f: f.led_index)
    images = np.stack([image_to_array(f.image) for f in frames])
    directions = np.array([[d.x, d.y, d.z] for d in lights.directions])
    intensities = np.asarray(lights.relative_intensities, dtype=np.float64)
    options = ReconstructionOptions(model=Model.HK, enhance=True)
    prepared = prepare_calibration(
        optical_to_ps(directions),
        camera_matrix=np.asarray(burst.camera_info.k, dtype=np.float64).reshape(3, 3),
        shape=images.shape[1:], intensities=intensities, options=options)
    result = reconstruct_prepared(images, prepared, full_scale=255.0, options=options,
                                  hk_initial_scale=initial_scale)
    return ps_to_optical(result.normals_ps).astype(np.float32), result.hk_scale


def test_replayed_bursts_reconstruct_as_live(session_bag: Path, ros_node: Node, start_node,
                                             spin_until) -> None:
    received: dict[int, Image] = {}
    ros_node.create_subscription(Image, f"{NS}/{topics.NORMALS}",
                                 lambda m: received.setdefault(m.header.stamp.sec, m),
                                 qos.OUTPUT_QOS)
    recon = start_node("fingerps_recon", "recon_node")
    recon.wait_in_graph(ros_node, "recon", NS)
    replay = start_node("fingerps_recon", "bag_replay", "--ros-args",
                        "-p", f"bag:={session_bag}", "-p", "wait_for_subscribers:=1")
    # recon_node loads its kernels first (longer on one thread of a loaded machine); the
    # bursts wait for it in its queue.
    spin_until(lambda: len(received) == 2, "recon's normals of both replayed bursts",
               timeout=90.0)
    assert replay.wait() == 0, replay.output
    assert "replay done: 3 messages published" in replay.output

    reader = SessionBagReader(session_bag)
    lights = reader.latest(LIGHTS_TOPIC)
    scale = None
    for message in reader.messages([BURST_TOPIC]):
        burst = message.deserialize()
        live = image_to_array(received[burst.header.stamp.sec])
        direct, scale = _direct_normals(lights, burst, scale)
        assert np.array_equal(live, direct)
        assert np.count_nonzero(live.any(axis=2)) > 1000


def test_start_offset_and_topic_filter(session_bag: Path, ros_node: Node, start_node,
                                       spin_until) -> None:
    bursts: list[int] = []
    ros_node.create_subscription(Burst, BURST_TOPIC, lambda m: bursts.append(m.burst_id),
                                 qos.BURST_QOS)
    lights: list[LightCalibration] = []
    ros_node.create_subscription(LightCalibration, LIGHTS_TOPIC, lights.append,
                                 qos.CALIBRATION_QOS)
    replay = start_node("fingerps_recon", "bag_replay", "--ros-args",
                        "-p", f"bag:={session_bag}", "-p", "start:=1.5", "-p", "rate:=0.0",
                        "-p", "wait_for_subscribers:=1")
    spin_until(lambda: bursts and lights, "the burst after start and the calibration")
    assert replay.wait() == 0, replay.output
    spin_until(lambda: True, "a last spin")
    assert bursts == [2] and len(lights) == 1  # calibration in force at start is published

    only = start_node("fingerps_recon", "bag_replay", "--ros-args",
                      "-p", f"bag:={session_bag}", "-p", "rate:=0.0",
                      "-p", f"topics:=[{LIGHTS_TOPIC}]")
    assert only.wait() == 0
    assert "replay done: 1 messages published" in only.output


def test_waiting_for_a_late_subscriber_keeps_the_recorded_spacing(
        session_bag: Path, ros_node: Node, start_node, spin_until) -> None:
    """The bursts' subscriber joins seconds after the replay started: the first burst waits
    for it, the calibration is there before it, and the second still follows a recorded
    second later (not at once, as it would if the wait counted as playing time)."""
    replay = start_node("fingerps_recon", "bag_replay", "--ros-args",
                        "-p", f"bag:={session_bag}", "-p", "wait_for_subscribers:=1")
    lights: list[LightCalibration] = []
    ros_node.create_subscription(LightCalibration, LIGHTS_TOPIC, lights.append,
                                 qos.CALIBRATION_QOS)
    spin_until(lambda: lights, "the calibration, before any burst subscriber exists")
    wait_until_s = time.monotonic() + 2.5  # held past both bursts' recorded times
    spin_until(lambda: time.monotonic() > wait_until_s, "the late subscriber's moment")
    arrivals: list[tuple[int, float, int]] = []
    ros_node.create_subscription(
        Burst, BURST_TOPIC,
        lambda m: arrivals.append((m.burst_id, time.monotonic(), len(lights))), qos.BURST_QOS)
    spin_until(lambda: len(arrivals) == 2, "both bursts for the late subscriber")
    assert replay.wait() == 0, replay.output
    (first, t1, lights_then), (second, t2, _) = arrivals
    assert (first, second) == (1, 2) and lights_then == 1
    assert t2 - t1 > 0.5, f"the second burst came {t2 - t1:.3f} s after the first"


def test_a_bag_of_another_message_version_is_refused(tmp_path: Path, installed) -> None:
    real = load_message_definition("fingerps_msgs/msg/Burst")
    old = MessageDefinition(real.type_name, real.encoding,
                            real.text.replace("uint32 burst_id", "uint16 burst_id", 1))
    assert old.text != real.text
    with SessionBagWriter(tmp_path / "old") as bag:
        bag.add_topic(BURST_TOPIC, "fingerps_msgs/msg/Burst", offered_qos_yaml="[]",
                      definition=old)
        bag.write(BURST_TOPIC, b"\x00\x01\x00\x00", log_time_ns=T0, publish_time_ns=T0)
    result = subprocess.run([str(installed("fingerps_recon", "bag_replay")), "--ros-args",
                             "-p", f"bag:={tmp_path / 'old'}"],
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 1, result.stdout + result.stderr
    output = result.stdout + result.stderr
    assert "another version of fingerps_msgs/msg/Burst" in output
    assert "Traceback" not in output
