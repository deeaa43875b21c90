"""The QoS profiles of the fingerps graph, named once (REP-2003).

- Camera images (tagged frames, plain images, camera info): the sensor-data profile,
  best effort and shallow, so a slow viewer never stalls capture.
- Bursts and reconstruction outputs: reliable and volatile, a few deep. A burst is one
  message of seven images; losing a fragment would lose the whole unit of work.
- Calibration (light directions, flat-field maps): reliable and transient-local with
  depth 1, so a node that starts later still receives the calibration in force.
"""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

SENSOR_QOS: QoSProfile = qos_profile_sensor_data

BURST_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=4,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

OUTPUT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=4,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

CALIBRATION_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
