"""The calibration in force (``reconstruction.calibration_in_force``), shared by recon_node's
worker and scan_node: what it takes, what it refuses and keeps, whether a flat field fits,
and scan_node (a real node, in this process) refusing what recon_node refuses."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Vector3
from rclpy.node import Node

from fingerps_driver.simulation import SimulatedRig
from fingerps_msgs.msg import FlatField, LightCalibration
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions
from fingerps_recon.reconstruction.burst_intake import BurstLimits
from fingerps_recon.reconstruction.calibration_in_force import (
    FLAT_FIELD,
    LIGHTS,
    CalibrationInForce,
)
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image

OPTIONS = ReconstructionOptions(model=Model.LAMBERT)


def lights(rig: SimulatedRig, directions_ps: np.ndarray | None = None) -> LightCalibration:
    dirs = ps_to_optical(rig.light_directions_ps() if directions_ps is None else directions_ps)
    return LightCalibration(camera_name="test", directions=[
        Vector3(x=float(x), y=float(y), z=float(z)) for x, y, z in dirs])


def flat(maps: np.ndarray) -> FlatField:
    return FlatField(camera_name="test",
                     maps=[array_to_image(m, encoding="32FC1") for m in maps],
                     relative_intensities=[1.0] * len(maps))


def test_a_refused_calibration_keeps_the_one_in_force_and_its_reason(rig: SimulatedRig) -> None:
    held = CalibrationInForce()
    with pytest.raises(FingerpsError):
        held.offer_lights(lights(rig, np.zeros((7, 3))))
    assert held.lights is None and held.refused_count == 1 and LIGHTS in held.refused
    with pytest.raises(FingerpsError, match=r"the last one was refused: .*calibrate_lights"):
        held.require_lights()
    good = lights(rig)
    assert held.offer_lights(good) is good and held.require_lights() is good
    assert held.refused == {}
    with pytest.raises(FingerpsError):
        held.offer_flat(FlatField(maps=[]), BurstLimits())
    assert held.refused_count == 2 and set(held.refused) == {FLAT_FIELD}
    assert held.lights is good and held.flat_maps is None


def test_a_flat_field_is_used_only_where_it_fits(rig: SimulatedRig) -> None:
    held = CalibrationInForce()
    held.offer_lights(lights(rig))
    h, w = rig.camera.height, rig.camera.width
    maps = held.offer_flat(flat(np.full((7, h, w), 0.5, np.float32)), BurstLimits())
    assert held.flat_for((7, h, w)) is maps
    for other in ((7, h, w + 1), (6, h, w), (8, h, w)):
        assert held.flat_for(other) is None
    k = rig.camera_matrix
    with_flat, _ = held.prepare(held.lights, k, (h, w), OPTIONS)
    assert with_flat.flat_gain is not None
    # another camera mode: prepared without the flat field, not refused
    smaller, _ = held.prepare(held.lights, k, (h // 2, w // 2), OPTIONS)
    assert smaller.flat_gain is None and held.prepared.count == 2


def test_scan_node_refuses_what_recon_refuses(rig: SimulatedRig, ros_node: Node) -> None:
    from fingerps_recon import scan_node

    node = scan_node.ScanNode(context=ros_node.context)
    try:
        node._on_lights(lights(rig, np.full((7, 3), np.nan)))
        assert node._calibration.lights is None and node._calibration.refused_count == 1
        node._on_flat(flat(np.full((7, 20, 30), -1.0, np.float32)))
        assert node._calibration.flat_maps is None and node._calibration.refused_count == 2
        good = lights(rig)
        node._on_lights(good)
        assert node._calibration.lights is good
    finally:
        node.destroy_node()
