"""recorder_node: records a fingerps session into a rosbag2 MCAP bag.

Subscribes to the session topics with ``raw=True`` (the serialized CDR bytes are written as
they arrive, nothing is deserialized) using each topic's QoS from `fingerps_ros.qos`
(calibration topics reliable + transient-local, so the calibration in force when recording
starts is recorded too), and writes them with `fingerps_recon.sessions.session_bag.SessionBagWriter`
into ``<bags_dir>/<session_name>/`` (``metadata.yaml`` + ``<session_name>_0.mcap``, and
``_1.mcap``, ... when split), which ``ros2 bag info/play``, rosbags and Foxglove read.

At kiosk scale: ``max_bagfile_size`` / ``max_bagfile_duration`` split the bag into pieces as
rosbag2's options of the same names do (each piece a complete MCAP file, all listed in
metadata.yaml), and ``bags_dir_limit_mb`` caps the sessions in ``bags_dir``: the oldest whole
sessions are removed first (`sessions.session_retention`), at start, at each new piece
and every ``RETENTION_PERIOD_S`` seconds, never the session being recorded.

Nothing is lost silently: a message the recorder subscribed to and did not write is counted
per topic and reason (``lost_before_recorder``, ``dropped_writer_behind``, ``write_errors``,
``unrecordable``), on ``/diagnostics`` (status ``recorder: recording``, WARN while losses
keep happening, ERROR while writes fail) and in the finished bag. The intake, the writer
thread and its bounded queue, the counting and the retention are the plain
`fingerps_recon.sessions.session_recorder.SessionRecorder`; this node subscribes, stamps
and hands it the messages.

Shutdown: SIGINT and SIGTERM both shut the rclpy context down (rclpy Jazzy installs handlers
for both), the spin ends, and ``destroy_node()`` drains the queue and finishes the bag, so
the MCAP file gets its summary and the directory its metadata.yaml. A killed process
(SIGKILL) loses the open chunk at most; ``ros2 run fingerps_recon bag_recover <bag>``
(`fingerps_recon.sessions.bag_recovery`) turns the rest into a valid bag and says what was lost.

MCAP metadata records: ``fingerps.software`` (package version, ROS distro, RMW, Python,
mcap library) and ``fingerps.recorder.parameters`` (every parameter in force). The
calibration used is in the bag as the calibration topics' messages.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any

import rclpy.logging
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from rclpy.utilities import get_rmw_implementation_identifier

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.sessions.bag_reader import message_class
from fingerps_recon.sessions.message_definition import load_message_definition
from fingerps_recon.sessions.recorder_parameters import recorder_parameters
from fingerps_recon.sessions.rosbag2_qos import QosProfileFields
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_recon.sessions.session_metadata import (
    parameters_record,
    ros_distro,
    software_record,
)
from fingerps_recon.sessions.session_recorder import MiB, SessionRecorder
from fingerps_recon.sessions.session_topics import (
    choose_topics,
)
from fingerps_ros import topics
from fingerps_ros.diagnostics import PERIOD_S, DiagnosticsPublisher, key_values
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import declare_parameters
from fingerps_ros.time_conversion import NS_PER_S


class RecorderNode(Node):
    """Records the session topics into ``<bags_dir>/<session_name>`` (rosbag2 MCAP)."""

    def __init__(self) -> None:
        super().__init__("recorder", namespace=topics.NAMESPACE)
        checks = declare_parameters(self, recorder_parameters(self.resolve_topic_name))
        checks.refuse_unknown_overrides(self)

        self._shutdown_logger = rclpy.logging.get_logger(f"{self.get_logger().name}.bag")
        self._use_sim_time = bool(self.get_parameter("use_sim_time").value)
        # Everything that can fail on bad input happens before the bag directory is made.
        record = choose_topics(self.get_parameter("topics").value or [],
                               record_outputs=bool(self.get_parameter("record_outputs").value),
                               resolve=self.resolve_topic_name)
        for type_name in sorted({spec.type_name for spec in record.values()}):
            load_message_definition(type_name)  # fail now, not at the first message
        classes = {topic: message_class(spec.type_name) for topic, spec in record.items()}
        bags_dir = Path(str(self._value("bags_dir")))
        bag = SessionBagWriter(
            bags_dir / str(self._value("session_name")),
            chunk_size=int(self._value("chunk_size")), ros_distro=ros_distro(),
            max_bagfile_size=int(self._value("max_bagfile_size")),
            max_bagfile_duration_ns=int(self._value("max_bagfile_duration")) * NS_PER_S)
        self._recorder = SessionRecorder(
            bag, record, bags_dir=bags_dir,
            bags_dir_limit_bytes=int(self._value("bags_dir_limit_mb")) * MiB,
            queue_limit_bytes=int(self._value("queue_limit_mb")) * MiB,
            flush_period_s=lambda: float(self._value("flush_period")),
            publishers=self.count_publishers, offered_qos=self._offered_qos,
            logger=self.get_logger(), writer_logger=self._shutdown_logger)
        self._finished = False
        self._subscriptions_made: list[Any] = []
        self._diagnostics = DiagnosticsPublisher(self, self._statuses)
        self.create_timer(PERIOD_S, self._diagnostics.publish)

        self._recorder.start({
            "fingerps.software": software_record(
                node=self.get_fully_qualified_name(),
                rmw_implementation=get_rmw_implementation_identifier()),
            "fingerps.recorder.parameters": parameters_record(
                {name: param.value
                 for name, param in self.get_parameters_by_prefix("").items()}),
        })
        try:
            depth = int(self._value("history_depth"))
            for topic, spec in record.items():
                self._subscriptions_made.append(self.create_subscription(
                    classes[topic], topic, functools.partial(self._on_message, topic),
                    spec.subscription_qos(depth), raw=True))
        except BaseException:
            self.finish_bag()
            raise
        self.get_logger().info(
            f"recording {len(record)} topics into {bag.path.resolve()}: "
            f"{', '.join(record)}")

    def _value(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _offered_qos(self, topic: str) -> list[QosProfileFields]:
        """The QoS the topic's publishers offer, as the graph shows them."""
        return [QosProfileFields.from_profile(info.qos_profile)
                for info in self.get_publishers_info_by_topic(topic)]

    def _on_message(self, topic: str, data: bytes, info: dict[str, int]) -> None:
        """Subscription callback: stamp and hand over to the recorder. Nothing else.

        Log time is the receive time (the node clock's with use_sim_time), publish time the
        source time, as rosbag2 records them.
        """
        if self._use_sim_time:
            received = self.get_clock().now().nanoseconds
        else:
            received = int(info.get("received_timestamp", 0)) or time.time_ns()
        self._recorder.receive(topic, data, log_time_ns=received,
                               publish_time_ns=int(info.get("source_timestamp", 0)),
                               sequence=info.get("publication_sequence_number"))

    def finish_bag(self) -> None:
        """Stop intake, drain the queue, finish the bag and log what it holds (idempotent)."""
        if self._finished:
            return
        self._finished = True
        for subscription in self._subscriptions_made:
            self.destroy_subscription(subscription)
        self._recorder.finish(self.get_logger() if self.context.ok() else self._shutdown_logger)

    def not_written(self) -> dict[str, dict[str, int]]:
        """Messages subscribed to and not written, per topic and reason (no zero entries)."""
        return self._recorder.not_written()

    def _statuses(self) -> list[DiagnosticStatus]:
        health = self._recorder.health()
        return [DiagnosticStatus(name=f"{self.get_name()}: recording",
                                 level=bytes([health.level]), message=health.message,
                                 values=key_values(health.values))]

    def destroy_node(self) -> None:
        """Finish the bag (so SIGINT and SIGTERM leave a valid bag), then destroy the node."""
        self.finish_bag()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon recorder_node``; returns the exit code.

    Exit code 2 with one line (no traceback) when the recorder cannot start, e.g. a
    bags_dir that cannot be created or a bag directory that already exists.
    """
    return run_node(RecorderNode, args=args, name="recorder_node",
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
