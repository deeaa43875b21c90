"""How the reconstruction's per-pixel kernels are compiled (numba), in one place.

Every kernel is ``numba.njit`` with IEEE arithmetic (``fastmath=False``), numpy's error
model (a division by zero gives inf/NaN, not an exception), the GIL released (the node's
executor keeps taking messages meanwhile) and numba's on-disk cache (``cache=True``:
``__pycache__`` beside the source when writable, else the user's cache directory, or
``NUMBA_CACHE_DIR``), so that a process loads instead of compiling
(:mod:`photometric.kernel_warm_up`). Where no cache directory is writable the kernel is
compiled in every process, and a warning says how to give it one.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numba

_OPTIONS = {"fastmath": False, "error_model": "numpy", "nogil": True}


def _compile(fn: Callable, **options: object) -> Callable:
    options = {**_OPTIONS, **options}
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError as exc:  # "cannot cache function ...: no locator available"
        warnings.warn(f"kernel {fn.__module__}.{fn.__name__} is not cached on disk ({exc}); "
                      "set NUMBA_CACHE_DIR to a writable directory to cache it", stacklevel=3)
        return numba.njit(cache=False, **options)(fn)


def parallel_kernel(fn: Callable) -> Callable:
    """A kernel that runs its ``prange`` loop (over chunks of pixels) on numba's threads
    (:func:`fingerps_recon.photometric.kernel_threads.numba_threads`)."""
    return _compile(fn, parallel=True)


def serial_kernel(fn: Callable) -> Callable:
    """A compiled helper of the kernels, run on one chunk."""
    return _compile(fn)


def inline_kernel(fn: Callable) -> Callable:
    """Scalar arithmetic or a part of a kernel inlined into its caller (numba IR): no call
    per chunk or pixel, and loops that LLVM still vectorises."""
    return _compile(fn, inline="always")
