"""Keeping freed memory in the process between bursts (glibc's malloc).

A burst's reconstruction allocates and frees the same few dozen arrays of 0.3-7 MB every
time (images' float copies, normals, depth, points, the print). glibc's malloc gives freed
memory back to the kernel when the free space at the top of a heap passes a threshold
(``M_TRIM_THRESHOLD``, 128 KiB, adjusted as blocks come and go) and serves large blocks from
fresh ``mmap`` pages (``M_MMAP_THRESHOLD``, dynamic): once that happens, every new burst
touches fresh pages, one page fault each (26 MB, some 6 700 faults, per HK burst in
``bench/bench_recon_speed.py`` after the stages before it), which costs the most on a
virtual machine whose host is busy. :func:`retain_freed_memory` fixes both thresholds, so
that blocks below 32 MiB come from the heaps and freed memory stays in the process (up to
``TRIM_THRESHOLD_BYTES`` free at a heap's top) for the next burst.

Importing :mod:`fingerps_recon.photometric.pipeline` calls it. Elsewhere than glibc (musl,
macOS) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Free memory a heap keeps at its top before giving it back to the kernel.
TRIM_THRESHOLD_BYTES = 256 << 20
#: Blocks at least this large are mapped on their own (glibc's largest allowed value on
#: 64-bit machines): the calibration's per-pixel lighting, not a burst's arrays.
MMAP_THRESHOLD_BYTES = 32 << 20

_DONE: list[bool] = []


def retain_freed_memory() -> bool:
    """Set glibc's trim and mmap thresholds (module docstring) once per process; True if
    they are set (now or before), False where the C library is not glibc."""
    if _DONE:
        return _DONE[0]
    ok = False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        pass
    else:
        mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        mallopt.restype = ctypes.c_int
        # Both thresholds: setting one turns off glibc's adjustment of the other.
        ok = bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)) and bool(
            mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    _DONE.append(ok)
    return ok
