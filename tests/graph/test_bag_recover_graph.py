"""A real recorder_node killed with SIGKILL mid-session: ``bag_recover`` (the installed
command) turns what it left into a valid bag holding every message that reached the file."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

from mcap.records import Channel, Message
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader as RosbagsReader

from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon.errors import McapDamageError
from fingerps_recon.sessions.mcap_records import scan_records
from fingerps_ros import topics

NAMESPACE = "/" + topics.NAMESPACE
BURST_TOPIC = f"{NAMESPACE}/{topics.BURST}"
LIGHTS_TOPIC = f"{NAMESPACE}/{topics.LIGHT_CALIBRATION}"
BURSTS = 6


def _burst_ids_on_disk(path: Path) -> list[int]:
    """Burst ids already in the file being written (intact records only; a chunk still
    being written reads as damage at the end of the file)."""
    ids: list[int] = []
    if not path.exists():
        return ids
    burst_channels = set()
    try:
        for item in scan_records(path):
            record = item.record
            if isinstance(record, Channel) and record.topic == BURST_TOPIC:
                burst_channels.add(record.id)
            elif isinstance(record, Message) and record.channel_id in burst_channels:
                ids.append(deserialize_message(record.data, Burst).burst_id)
    except McapDamageError:
        pass
    return ids


def test_a_sigkilled_recorder_bag_is_recovered(start_recorder, wait_for, installed) -> None:
    recorder, burst_pub, bags = start_recorder(
        "killed", lights=LightCalibration(camera_name="killed", sphere_radius=0.004),
        flush_period=0.05)

    mcap_path = bags / "killed" / "killed_0.mcap"
    for burst_id in range(BURSTS):  # one at a time: the burst QoS keeps only the last 4
        burst_pub.publish(Burst(burst_id=burst_id))
        wait_for(lambda n=burst_id: len(_burst_ids_on_disk(mcap_path)) > n,
                 f"burst {burst_id} in the bag file (flush_period 0.05 s)")

    recorder.send_signal(signal.SIGKILL)
    assert recorder.wait() == -signal.SIGKILL
    assert not (bags / "killed" / "metadata.yaml").exists()  # it never finished
    on_disk = _burst_ids_on_disk(mcap_path)

    result = subprocess.run(
        [str(installed("fingerps_recon", "bag_recover")), str(bags / "killed")],
        capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    assert "recovered" in result.stdout and "Traceback" not in result.stderr
    # killed between flushes: nothing damaged, nothing lost, and the report says so
    assert "damage : none" in result.stdout and "lost   : no messages" in result.stdout
    fixed = bags / "killed_recovered"
    assert sorted(p.name for p in fixed.iterdir()) == ["killed_recovered_0.mcap",
                                                      "metadata.yaml"]
    with RosbagsReader(fixed) as bag:
        counts = {c.topic: c.msgcount for c in bag.connections}
        ids = [deserialize_message(raw, Burst).burst_id
               for conn, _, raw in bag.messages() if conn.topic == BURST_TOPIC]
    assert ids == on_disk == list(range(BURSTS))
    assert counts == {BURST_TOPIC: BURSTS, LIGHTS_TOPIC: 1}
