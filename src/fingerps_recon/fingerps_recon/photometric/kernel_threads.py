"""How many threads the reconstruction's per-pixel kernels run on.

One setting for every solver (the compiled HK and Lambertian kernels, the HK solver's numpy
backend): at most :func:`thread_limit` threads, by default every core this process may run
on. ``recon_node``'s ``threads`` parameter sets it (:func:`set_thread_limit`): on a machine
whose other cores are busy (the driver, a recorder), one thread can finish a burst sooner
than two that wait for each other at every pass (``bench/bench_e2e.py`` measures both).

Between kernels numba's threads sleep: importing this module sets ``OMP_WAIT_POLICY`` to
``PASSIVE`` unless the environment sets it. numba's OpenMP threading layer (the one it picks
where TBB is not installed) otherwise keeps its idle threads spinning for some 10 ms after
each kernel, which on two cores takes the core that the ridge enhancement, the integration,
the output thread or the driver should have (``bench/bench_recon_speed.py``). libgomp reads
the variable when it is loaded, at numba's first parallel launch: a process that loaded it
before (another library's OpenMP) keeps its own policy.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

_LIMIT: list[int] = [0]  # 0: every available core


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def set_thread_limit(threads: int) -> None:
    """Run the kernels on at most ``threads`` threads (0: every available core)."""
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise ValueError(f"threads must be an integer >= 0 (0 = every core), got {threads!r}")
    _LIMIT[0] = threads


def thread_limit() -> int:
    """The threads the kernels run on now: the limit set, at most the available cores."""
    cores = available_cores()
    return min(_LIMIT[0], cores) if _LIMIT[0] else cores


@contextmanager
def numba_threads() -> Iterator[int]:
    """numba's threads for the calling thread set to :func:`thread_limit` (at most numba's
    pool), chunks of pixels dealt out one at a time as threads free up (another process may
    hold a core); restored on exit. Yields the number of threads."""
    import numba

    saved = (numba.get_num_threads(), numba.get_parallel_chunksize())
    threads = max(1, min(thread_limit(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(threads)
    numba.set_parallel_chunksize(1)
    try:
        yield threads
    finally:
        numba.set_num_threads(saved[0])
        numba.set_parallel_chunksize(saved[1])
