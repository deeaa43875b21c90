"""Rolled prints of synthetic fingers' true depth on the simulated rig: the prints the
pipeline makes of a perfect reconstruction, for the tests of what consumes prints."""

from __future__ import annotations

import numpy as np

from fingerps_driver.simulation import FingertipShape, RigConfig, SimulatedRig
from fingerps_recon.surface.rolled_print import rolled_print


def true_rolled_print(identity: int) -> np.ndarray:
    """(H, W) uint8, 500 ppi: the rig's print of fingerprint ``identity`` (about 374 x 296)."""
    rig = SimulatedRig(RigConfig(finger=FingertipShape(identity=identity)))
    truth = rig.finger_truth()
    return rolled_print(truth.depth_m, mask=truth.mask, camera_matrix=rig.camera_matrix,
                        normals_ps=truth.normals_ps).image
