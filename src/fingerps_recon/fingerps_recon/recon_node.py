"""recon_node: complete bursts in; normals, normal map, depth and a point cloud out.

Thin ROS adapter around ``fingerps_recon.reconstruction.worker.ReconstructionWorker``, which
reconstructs with ``fingerps_recon.photometric.pipeline.reconstruct_prepared``. The burst
callback only enqueues; a worker thread reconstructs, so a slow reconstruction never blocks
intake. The queue is bounded and drops the oldest burst, and the drops are counted. The
worker first warms the compiled kernels (``/diagnostics`` says ``ready`` once it has), and
prepares the calibration for the bursts' camera once, when the calibration, the
camera_info or the image size changes (``calibration_in_force.CalibrationInForce``).

Every message is survived: a burst beyond the size bounds (``max_image_width``,
``max_image_height``, ``max_burst_frames``) is refused on arrival, before it is queued; a
light calibration or flat field that cannot determine normals is refused on arrival (the
previous one stays in force); anything else a burst raises, expected or not, is logged in
one line naming the burst and counted, and the worker goes on with the next burst. An
empty reconstruction is a failure, not a done burst. ``/diagnostics`` is WARN while one of
the last ``health_window`` bursts failed (or a refused calibration was not replaced), ERROR
when all of them failed, OK once good bursts flow again.

Here: the parameters (``reconstruction.parameters``), the subscriptions and publishers with
their QoS, the outputs' messages (``reconstruction.outputs``) and ``/diagnostics``
(``reconstruction.diagnostics``).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.reconstruction.diagnostics import reconstruction_status
from fingerps_recon.reconstruction.outputs import OUTPUT_TOPICS, Output
from fingerps_recon.reconstruction.parameters import PARAMETERS, follow_threads, read_settings
from fingerps_recon.reconstruction.worker import ReconSettings, ReconstructionWorker
from fingerps_ros import qos, topics
from fingerps_ros.compressed_topics import CompressedTopics
from fingerps_ros.diagnostics import PERIOD_S, DiagnosticsPublisher
from fingerps_ros.node_runner import run_node
from fingerps_ros.parameters import declare_parameters


class ReconNode(Node):
    """Reconstructs every complete burst with the calibration in force."""

    def __init__(self, **node_options: object) -> None:
        """``node_options``: rclpy ``Node`` keywords (a test gives its ``context``)."""
        super().__init__("recon", namespace=topics.NAMESPACE, **node_options)
        checks = declare_parameters(self, PARAMETERS)
        # image_transport-style companions (normal_map/compressed, fingerprint/compressed,
        # depth/compressedDepth): encoded only while subscribed (compressed_topics.py)
        self._compressed = {
            name: CompressedTopics(self, name, qos.OUTPUT_QOS, checks,
                                   depth=name == topics.DEPTH)
            for name in (topics.NORMAL_MAP, topics.FINGERPRINT, topics.DEPTH)}
        checks.refuse_unknown_overrides(self)
        follow_threads(self)

        g = self.get_parameter
        self._recon = ReconstructionWorker(
            self._settings, self._publish, self.get_logger(),
            queue_depth=int(g("queue_depth").value), health_window=int(g("health_window").value))
        recon, guarded = self._recon, self._recon.guarded
        self.create_subscription(Burst, topics.BURST, guarded("burst", recon.on_burst),
                                 qos.BURST_QOS)
        self.create_subscription(LightCalibration, topics.LIGHT_CALIBRATION,
                                 guarded("light calibration", recon.on_lights),
                                 qos.CALIBRATION_QOS)
        self.create_subscription(FlatField, topics.FLAT_FIELD,
                                 guarded("flat field", recon.on_flat), qos.CALIBRATION_QOS)
        self.create_subscription(CameraInfo, topics.CAMERA_INFO,
                                 guarded("camera_info", recon.on_camera_info), qos.SENSOR_QOS)
        self._publishers_by_topic = {
            topic: self.create_publisher(PointCloud2 if topic == topics.POINTS else Image, topic,
                                         qos.OUTPUT_QOS)
            for topic in (*OUTPUT_TOPICS, topics.FINGERPRINT)}
        self._diagnostics = DiagnosticsPublisher(self, self._statuses)
        self.create_timer(PERIOD_S, guarded("diagnostics", self._diagnostics.publish))
        self._worker = threading.Thread(target=recon.run, name="recon_worker")
        self._worker.start()
        self.get_logger().info("recon ready: waiting for a light calibration and bursts")

    def _wanted(self) -> list[str]:
        """The outputs someone subscribes to now, raw or compressed."""
        publishers = self._publishers_by_topic
        return [topic for topic in OUTPUT_TOPICS
                if publishers[topic].get_subscription_count() > 0
                or (topic in self._compressed and self._compressed[topic].watched)]

    def _settings(self) -> ReconSettings:
        """The parameters as they are now, and the outputs someone watches; the ridge
        enhancement (Eq. 12, for the normal map only) is skipped while nobody subscribes to
        the normal map."""
        wanted = tuple(self._wanted())
        settings = replace(read_settings(self), wanted=wanted)
        if settings.options.enhance and topics.NORMAL_MAP not in wanted:
            settings = replace(settings, options=replace(settings.options, enhance=False))
        return settings

    def _publish(self, outputs: Iterable[Output]) -> None:
        """Publish a burst's outputs as the worker builds them (raw), then their compressed
        companions."""
        companions: list[Output] = []
        for output in outputs:
            self._publishers_by_topic[output.topic].publish(output.message)
            if output.topic in self._compressed:
                companions.append(output)
        for output in companions:  # after the raw ones
            self._compressed[output.topic].publish(output.array, output.encoding,
                                                   output.message.header)

    def _statuses(self) -> list[DiagnosticStatus]:
        failures = sum(c.failures for c in self._compressed.values())
        return [reconstruction_status(self.get_name(), self._recon,
                                      compressed_failures=failures)]

    def destroy_node(self) -> None:
        """Stop the worker (it finishes the burst in hand) and destroy the node."""
        self._recon.stop()
        if self._worker.is_alive():
            self._worker.join(timeout=60.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon recon_node``."""
    return run_node(ReconNode, args=args, name="recon_node",
                    expected_errors=(FingerpsReconError,))


if __name__ == "__main__":
    raise SystemExit(main())
