"""The rolled-equivalent print through the graph: a burst in, a 500 ppi fingerprint out.

recon_node runs as a real process with ``fingerprint:=true``; the test plays the driver and
the calibration (as tests/graph/test_recon_graph.py does) with bursts of a synthetic finger
(``FingertipShape.identity``). The print must arrive on ``fingerprint`` with the burst's
stamp, as mono8 in the frame that names its resolution, be as large as a fingertip at
500 ppi and carry dark ridges of the finger's period (how well it matches the finger's
ground-truth print is measured by bench/bench_fingerprint.py); a burst whose finger is too
small to unroll gives no print, a reason in /diagnostics and the other outputs all the same.
"""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2
from stamps import stamp_key
from test_recon_graph import NS, _diagnostic_values

from fingerps_driver.simulation import FingertipShape, RigConfig, Scene, SimulatedRig
from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_ros import qos, topics
from fingerps_ros.image_conversion import image_to_array

IDENTITY = 7
PX_PER_MM = 500 / 25.4


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(RigConfig(finger=FingertipShape(identity=IDENTITY)))


def _images(rig: SimulatedRig, seed: int, mask: np.ndarray | None = None) -> np.ndarray:
    images = rig.render_burst(Scene.FINGER, seed=seed)
    if mask is not None:  # only a small patch of the finger in view
        images = np.where(mask, images, images.min())
    return images


def _period_mm(image: np.ndarray, inside: np.ndarray) -> float:
    """Dominant ridge period of the print (peak of the radial spectrum)."""
    rows, cols = np.nonzero(inside)
    r0, c0 = (rows.min() + rows.max()) // 2, (cols.min() + cols.max()) // 2
    patch = image[r0 - 64:r0 + 64, c0 - 64:c0 + 64].astype(float)
    spectrum = np.abs(np.fft.fftshift(np.fft.fft2(patch - patch.mean()))) ** 2
    fy, fx = np.meshgrid(np.fft.fftshift(np.fft.fftfreq(128)),
                         np.fft.fftshift(np.fft.fftfreq(128)), indexing="ij")
    radius = np.hypot(fx, fy)
    band = (radius > 1 / 20) & (radius < 1 / 5)
    return float(1.0 / radius[band][np.argmax(spectrum[band])] / PX_PER_MM)


def test_a_burst_in_gives_a_500ppi_fingerprint_out(
        ros_node: Node, start_node, spin_until, rig: SimulatedRig, rig_messages) -> None:
    lights_pub = ros_node.create_publisher(
        LightCalibration, f"{NS}/{topics.LIGHT_CALIBRATION}", qos.CALIBRATION_QOS)
    lights_pub.publish(rig_messages.light_calibration("graph_test"))
    burst_pub = ros_node.create_publisher(Burst, f"{NS}/{topics.BURST}", qos.BURST_QOS)
    prints: dict[tuple[int, int], Image] = {}
    clouds: dict[tuple[int, int], PointCloud2] = {}
    ros_node.create_subscription(Image, f"{NS}/{topics.FINGERPRINT}",
                                 lambda m: prints.__setitem__(stamp_key(m.header), m),
                                 qos.OUTPUT_QOS)
    ros_node.create_subscription(PointCloud2, f"{NS}/{topics.POINTS}",
                                 lambda m: clouds.__setitem__(stamp_key(m.header), m),
                                 qos.OUTPUT_QOS)
    diagnostics: list[DiagnosticArray] = []
    ros_node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, diagnostics.append, 10)

    recon = start_node("fingerps_recon", "recon_node", "--ros-args",
                       "-p", "fingerprint:=true", "-p", "queue_depth:=4")
    recon.wait_in_graph(ros_node, "recon", NS)
    spin_until(lambda: burst_pub.get_subscription_count() >= 1, "recon's burst subscription")
    spin_until(lambda: any(v.get("ready") == "True" and v.get("calibrated") == "True"
                           for v in _diagnostic_values(diagnostics)),
               "recon ready and calibrated")

    good = rig_messages.burst(_images(rig, 100), 1)
    burst_pub.publish(good)
    spin_until(lambda: stamp_key(good.header) in prints, "the fingerprint of the burst", timeout=60)
    message = prints[stamp_key(good.header)]
    assert message.encoding == "mono8"
    assert message.header.frame_id == topics.FINGERPRINT_FRAME == "fingerps_rolled_print_500ppi"
    image = image_to_array(message)
    height_mm, width_mm = np.array(image.shape) / PX_PER_MM
    assert 10 < width_mm < 30 and 10 < height_mm < 30, (width_mm, height_mm)
    inside = image < 255
    assert inside.mean() > 0.4
    dark = (image < 128) & inside
    assert 0.3 < dark.sum() / inside.sum() < 0.7  # ridges and valleys, about half each
    period = _period_mm(image, inside)
    assert 0.35 < period < 0.6, period  # the generator's periods are 0.40-0.55 mm

    # A finger of which only a 4 mm square is in view: no print, a reason, outputs as usual.
    small = np.zeros((rig.camera.height, rig.camera.width), bool)
    cy, cx = rig.camera.height // 2, rig.camera.width // 2
    small[cy - 60:cy + 60, cx - 60:cx + 60] = True
    patch = rig_messages.burst(_images(rig, 200, mask=small), 2)
    burst_pub.publish(patch)
    spin_until(lambda: stamp_key(patch.header) in clouds, "the small patch's cloud", timeout=60)
    spin_until(lambda: any(int(v.get("fingerprints_rejected", 0)) >= 1
                           for v in _diagnostic_values(diagnostics)),
               "the rejected print counted")
    values = [v for v in _diagnostic_values(diagnostics)
              if int(v.get("fingerprints_rejected", 0)) >= 1][-1]
    assert "no fingerprint" in values["last_fingerprint_problem"]
    assert "mm" in values["last_fingerprint_problem"]  # it says how much finger there was
    assert stamp_key(patch.header) not in prints
    assert int(values["fingerprints_made"]) >= 1
    assert "Traceback" not in recon.output
