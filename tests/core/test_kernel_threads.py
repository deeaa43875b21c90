"""The kernels' idle threads sleep between kernels (photometric.kernel_threads).

OMP_WAIT_POLICY is read once, when numba loads its OpenMP layer, so each case runs in a
process of its own: it solves a burst with the parallel Lambertian kernel on two threads,
then sleeps, and reports the CPU time the process used while its main thread slept.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = r"""
import json, time
import numpy as np
from fingerps_recon.photometric.lambertian import solve_lambertian
from fingerps_recon.photometric import kernel_threads
import numba

kernel_threads.set_thread_limit(2)
rng = np.random.default_rng(0)
lights = np.array([[0.3 * np.cos(a), 0.3 * np.sin(a), 1.0] for a in np.linspace(0, 6, 7)])
lights /= np.linalg.norm(lights, axis=1, keepdims=True)
images = rng.uniform(20, 200, (7, 400, 400)).astype(np.float32)
for _ in range(3):
    solve_lambertian(images, lights)
start = time.process_time()
time.sleep(0.3)
print(json.dumps({"idle_cpu_s": time.process_time() - start,
                  "layer": numba.threading_layer(), "threads": numba.config.NUMBA_NUM_THREADS}))
"""


def _idle_cpu(policy: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    env["NUMBA_NUM_THREADS"] = "2"
    run = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_idle_kernel_threads_do_not_spin() -> None:
    quiet = _idle_cpu(None)  # the project's default
    # A sleeping process whose threads sleep uses next to no CPU; spinning threads use
    # their whole wait (numba's OpenMP layer by libgomp's default: some 10 ms a kernel).
    assert quiet["idle_cpu_s"] < 0.003, quiet
    if quiet["layer"] == "omp":
        # The probe sees spinning where there is some: the same process told to spin.
        spinning = _idle_cpu("ACTIVE")
        assert spinning["idle_cpu_s"] > 0.05, spinning
