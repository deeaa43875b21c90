"""recorder_node as a real process: it records what the test publishes, and a SIGINT or a
SIGTERM leaves a complete, readable bag.
"""

from __future__ import annotations

import signal
import struct
from pathlib import Path

import pytest
import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from rclpy.node import Node
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon import qos, topics

NAMESPACE = "/" + topics.NAMESPACE
BURST_TOPIC = f"{NAMESPACE}/{topics.BURST}"
LIGHTS_TOPIC = f"{NAMESPACE}/{topics.LIGHT_CALIBRATION}"
BURSTS = 3


def _messages_on_disk(path: Path) -> int:
    """Messages already in a bag file that is still being written."""
    if not path.exists():
        return 0
    count = 0
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                count += isinstance(record, Message)
        except (McapError, struct.error, EOFError):
            pass
    return count


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_recorder_writes_a_valid_bag_and_stops_cleanly(
        signum: int, ros_node: Node, start_node, wait_for, tmp_path: Path) -> None:
    # The calibration is published before the recorder exists: transient-local brings it.
    lights_pub = ros_node.create_publisher(LightCalibration, LIGHTS_TOPIC, qos.CALIBRATION_QOS)
    lights_pub.publish(LightCalibration(camera_name="graph_test", sphere_radius=0.005))
    burst_pub = ros_node.create_publisher(Burst, BURST_TOPIC, qos.BURST_QOS)

    bags = tmp_path / "bags"
    recorder = start_node(
        "fingerps_recon", "recorder_node", "--ros-args",
        "-p", f"bags_dir:={bags}", "-p", "session_name:=graph_session",
        "-p", "record_outputs:=false", "-p", "flush_period:=0.1")
    recorder.wait_in_graph(ros_node, "recorder", NAMESPACE)
    wait_for(lambda: burst_pub.get_subscription_count() >= 1, "the recorder's burst subscription")

    subscribed = dict(ros_node.get_subscriber_names_and_types_by_node("recorder", NAMESPACE))
    assert subscribed[BURST_TOPIC] == ["fingerps_msgs/msg/Burst"]
    assert f"{NAMESPACE}/{topics.POINTS}" not in subscribed  # record_outputs:=false

    for burst_id in range(BURSTS):
        burst_pub.publish(Burst(burst_id=burst_id))
    mcap_path = bags / "graph_session" / "graph_session_0.mcap"
    # flush_period 0.1 s: the messages reach the file soon after they are received.
    wait_for(lambda: _messages_on_disk(mcap_path) >= BURSTS + 1, "the messages in the bag file")

    recorder.send_signal(signum)
    assert recorder.wait() == 0, recorder.output
    assert "Traceback" not in recorder.output
    assert f"{BURSTS + 1} messages" in recorder.output  # the bag path and counts are logged

    bag_dir = bags / "graph_session"
    assert sorted(p.name for p in bag_dir.iterdir()) == ["graph_session_0.mcap",
                                                         "metadata.yaml"]
    with open(mcap_path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == BURSTS + 1
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {BURST_TOPIC, LIGHTS_TOPIC}
        offered = yaml.safe_load(channels[LIGHTS_TOPIC].metadata["offered_qos_profiles"])
        assert offered[0]["durability"] == "transient_local"
        assert offered[0]["reliability"] == "reliable"
        records = {m.name: m.metadata for m in reader.iter_metadata()}
        assert records["fingerps.software"]["package"] == "fingerps_recon"
        assert records["fingerps.recorder.parameters"]["session_name"] == "graph_session"
        assert records["fingerps.recorder.parameters"]["record_outputs"] == "false"
        assert "rosbag2" in records

    store = get_typestore(Stores.ROS2_JAZZY)
    with RosbagsReader(bag_dir) as bag:
        counts = {c.topic: c.msgcount for c in bag.connections}
        assert counts == {BURST_TOPIC: BURSTS, LIGHTS_TOPIC: 1}
        for connection in bag.connections:
            store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        values = {}
        for connection, _, raw in bag.messages():
            values.setdefault(connection.topic, []).append(
                store.deserialize_cdr(raw, connection.msgtype))
    assert sorted(b.burst_id for b in values[BURST_TOPIC]) == list(range(BURSTS))
    assert values[LIGHTS_TOPIC][0].camera_name == "graph_test"


def test_unwritable_bags_dir_is_one_line_and_exit_code_2(start_node, tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    recorder = start_node("fingerps_recon", "recorder_node", "--ros-args",
                          "-p", f"bags_dir:={blocker / 'bags'}")
    assert recorder.wait() == 2
    output = recorder.output
    assert "Traceback" not in output
    assert "cannot create bag directory" in output
    assert len([line for line in output.splitlines() if "error" in line.lower()]) == 1


def test_existing_session_is_refused(start_node, tmp_path: Path) -> None:
    (tmp_path / "bags" / "taken").mkdir(parents=True)
    recorder = start_node("fingerps_recon", "recorder_node", "--ros-args",
                          "-p", f"bags_dir:={tmp_path / 'bags'}", "-p", "session_name:=taken")
    assert recorder.wait() == 2
    assert "already exists" in recorder.output and "Traceback" not in recorder.output
