"""The HK solver's fixed settings (``photometric.hk_solver``): the floors of the model's
evaluation and derivatives, the tilt of initial normals facing away from the camera, the
Levenberg–Marquardt damping, and their float32 array as the compiled kernels take it."""

from __future__ import annotations

from types import ModuleType

import numpy as np

# 1/c_i and 1/c_r in the derivatives are capped at 1 / DERIVATIVE_FLOOR.
DERIVATIVE_FLOOR = 1e-3
# Smallest c_i used where the model is evaluated (avoids 1/0; changes f by < 1e-12 A p).
VALUE_FLOOR = 1e-12
# Initial normals facing away from the camera (v.n below this) are tilted to it.
MIN_INIT_CR = 0.05
# Levenberg–Marquardt damping: start, decrease on success, increase on failure, bounds.
LAMBDA_START = 1e-3
LAMBDA_DOWN = 1.0 / 3.0
LAMBDA_UP = 10.0
LAMBDA_MIN = 1e-9
LAMBDA_MAX = 1e9
N_SUMS = 15  # Gauss–Newton sums a pixel (hk_model_kernel.N_SUMS)


def kernel_consts(kernel: ModuleType) -> np.ndarray:
    """The kernels' float32 constants (floors, damping factors), indexed as in
    :mod:`photometric.hk_model_kernel`."""
    consts = np.zeros(kernel.N_CONSTS, np.float32)
    for index, value in (
        (kernel.VALUE_FLOOR, VALUE_FLOOR), (kernel.DERIVATIVE_FLOOR, DERIVATIVE_FLOOR),
        (kernel.LAMBDA_DOWN, LAMBDA_DOWN), (kernel.LAMBDA_UP, LAMBDA_UP),
        (kernel.LAMBDA_MIN, LAMBDA_MIN), (kernel.LAMBDA_MAX, LAMBDA_MAX),
    ):
        consts[index] = value
    return consts
