"""Reconstruction of one simulated burst (no ROS): per-stage time, median of 7 runs.

Also the accuracy of that reconstruction against the rig's ground truth, so a speed-up that
costs accuracy shows here.
"""

from __future__ import annotations

import numpy as np

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_recon.angular_error import angular_error_deg
from fingerps_recon.pipeline import ReconstructionOptions, reconstruct

RUNS = 7


def run() -> dict[str, float]:
    rig = SimulatedRig(RigConfig())
    rng = np.random.default_rng(1)
    images = np.stack([rig.render(Scene.FINGER, [k], rng=rng) for k in range(rig.led_count)])
    truth = rig.finger_truth()
    timings: dict[str, list[float]] = {}
    result = None
    for _ in range(RUNS):
        result = reconstruct(images, lights_ps=rig.light_directions_ps(),
                             camera_matrix=rig.camera_matrix, full_scale=rig.max_value(),
                             intensities=rig.light_intensities(),
                             options=ReconstructionOptions(enhance=True))
        for stage, ms in result.timings_ms.items():
            timings.setdefault(stage, []).append(ms)
    both = result.mask & truth.mask
    error = angular_error_deg(result.normals_ps, truth.normals_ps)[both]
    figures = {f"recon.lambert.{stage}_ms.median": float(np.median(values))
               for stage, values in timings.items()}
    figures["recon.lambert.mae_deg_true_lights"] = float(error.mean())
    return figures
