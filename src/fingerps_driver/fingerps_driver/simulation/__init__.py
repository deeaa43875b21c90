"""The simulated rig: synthetic fingertip, mirror sphere and white target under seven near LEDs.

The embedded default of fingerps and the ground truth of every accuracy figure. Public API::

    rig = SimulatedRig(RigConfig())
    frame = rig.render(Scene.FINGER, [k], rng=np.random.default_rng(0))
    truth = rig.finger_truth()

    rig = SimulatedRig(RigConfig(finger=FingertipShape(identity=3, roll_deg=10.0)))
    truth = rig.finger_truth()  # truth.rolled_mm: each pixel's point in the rolled plane
    card = rig.rolled_print()  # 500 ppi; rig.fingerprint.minutiae in the same plane
"""

from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.fingerprint_pattern import FingerprintPattern
from fingerps_driver.simulation.fingerprint_relief import RidgeRelief
from fingerps_driver.simulation.fingertip import FingertipShape
from fingerps_driver.simulation.led_field import LedLayout, LedRing
from fingerps_driver.simulation.mirror_sphere import MirrorSphere
from fingerps_driver.simulation.rig import FingerTruth, Scene, SimulatedRig
from fingerps_driver.simulation.rig_config import RigConfig
from fingerps_driver.simulation.sensor import SensorModel
from fingerps_driver.simulation.skin_reflectance import Reflectance, SkinReflectance
from fingerps_driver.simulation.white_target import WhiteTarget

__all__ = [
    "FingerTruth",
    "FingerprintPattern",
    "FingertipShape",
    "LedLayout",
    "LedRing",
    "MirrorSphere",
    "PinholeCamera",
    "Reflectance",
    "RidgeRelief",
    "RigConfig",
    "Scene",
    "SensorModel",
    "SimulatedRig",
    "SkinReflectance",
    "WhiteTarget",
]
