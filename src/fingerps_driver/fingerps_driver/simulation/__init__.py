"""The simulated rig: synthetic fingertip, mirror sphere and white target under seven near LEDs.

The embedded default of fingerps and the ground truth of every accuracy figure. Public API::

    rig = SimulatedRig(RigConfig())
    frame = rig.render(Scene.FINGER, [k], rng=np.random.default_rng(0))
    truth = rig.finger_truth()
"""

from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.fingertip import FingertipShape
from fingerps_driver.simulation.led_field import LedRing
from fingerps_driver.simulation.mirror_sphere import MirrorSphere
from fingerps_driver.simulation.rig import (
    FingerTruth,
    Reflectance,
    RigConfig,
    Scene,
    SimulatedRig,
)
from fingerps_driver.simulation.sensor import SensorModel
from fingerps_driver.simulation.white_target import WhiteTarget

__all__ = [
    "FingerTruth",
    "FingertipShape",
    "LedRing",
    "MirrorSphere",
    "PinholeCamera",
    "Reflectance",
    "RigConfig",
    "Scene",
    "SensorModel",
    "SimulatedRig",
    "WhiteTarget",
]
