"""driver_node with a synthetic fingerprint on the simulated finger (sim.finger_identity):
its frames show that finger, a pose change is taken, a bad pose refused with a reason."""

from __future__ import annotations

import signal

import cv2
import numpy as np
from rclpy.node import Node

from fingerps_driver.simulation import FingertipShape, RigConfig, Scene, SimulatedRig
from fingerps_msgs.srv import CaptureBurst
from fingerps_ros import topics
from fingerps_ros.image_conversion import image_to_array

NS = "/" + topics.NAMESPACE


def _first_frame(client, call_service) -> np.ndarray:
    response = call_service(client, CaptureBurst.Request(response_only=True), timeout=60.0)
    assert response.success, response.message
    return image_to_array(response.burst.frames[0].image).astype(np.float64)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _ridges(image: np.ndarray) -> np.ndarray:
    """The ridge band of an image: minus a 5 px box mean."""
    return image - cv2.blur(image, (5, 5))


def test_the_driver_shows_the_fingerprint_it_is_given_and_takes_a_new_pose(
        ros_node: Node, start_node, call_service, set_parameters) -> None:
    driver = start_node("fingerps_driver", "driver_node", "--ros-args",
                        "-p", "sim.finger_identity:=3")
    driver.wait_in_graph(ros_node, "driver", NS, timeout=60.0)
    capture = ros_node.create_client(CaptureBurst, f"{NS}/{topics.CAPTURE_BURST}")

    def set_roll(value: float):
        return set_parameters("driver", {"sim.finger_roll_deg": value}, timeout=60.0)[0]

    def ridge_match(frame: np.ndarray, config: RigConfig) -> float:
        reference = SimulatedRig(config).noiseless(Scene.FINGER, [0])
        return _correlation(_ridges(frame), _ridges(reference.astype(np.float64)))

    frame = _first_frame(capture, call_service)
    assert ridge_match(frame, RigConfig(finger=FingertipShape(identity=3))) > 0.5
    assert ridge_match(frame, RigConfig()) < 0.2  # not the spiral

    refused = set_roll(60.0)
    assert not refused.successful and "45" in refused.reason, refused.reason
    assert set_roll(8.0).successful
    frame = _first_frame(capture, call_service)
    assert ridge_match(frame, RigConfig(finger=FingertipShape(identity=3, roll_deg=8.0))) > 0.5
    assert ridge_match(frame, RigConfig(finger=FingertipShape(identity=3))) < 0.3

    driver.send_signal(signal.SIGTERM)
    assert driver.wait() == 0
