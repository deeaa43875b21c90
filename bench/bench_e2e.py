"""The whole graph end to end on the simulated rig (the demo, 10 bursts, separate processes).

e2e.bursts_per_s: reconstructed bursts per second while bursts are requested back to back;
e2e.latency_ms_median: burst complete (last frame captured) -> point cloud received;
e2e.mae_deg: mean angular error of the normals against ground truth inside the finger.
Each figure is the median over 3 runs of the demo.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix

RUNS = 3
NAMES = ("e2e.bursts_per_s", "e2e.latency_ms_median", "e2e.mae_deg")


def run() -> dict[str, float]:
    demo = Path(get_package_prefix("fingerps_driver")) / "lib/fingerps_driver/demo"
    collected: dict[str, list[float]] = {name: [] for name in NAMES}
    env = {**os.environ, "ROS_DOMAIN_ID": str(random.randint(1, 101)),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    for _ in range(RUNS):
        with tempfile.TemporaryDirectory() as tmp:
            figures_path = Path(tmp) / "figures.json"
            subprocess.run([str(demo), "--out", f"{tmp}/out", "--bags", f"{tmp}/bags",
                            "--bursts", "10", "--figures", str(figures_path)],
                           check=True, env=env, stdout=subprocess.DEVNULL)
            figures = json.loads(figures_path.read_text())
        for name in NAMES:
            collected[name].append(float(figures[name]))
    return {name: float(np.median(values)) for name, values in collected.items()}
