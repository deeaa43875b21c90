"""How the reconstruction's per-pixel kernels are compiled (numba), in one place.

Every kernel is ``numba.njit`` with IEEE arithmetic but one licence, ``contract``: LLVM may
fuse a multiplication and an addition into one FMA instruction (one rounding instead of
two: a result differs from the unfused one by about an ulp of each fused term; no
reassociation, no approximate division or functions, NaN and infinity kept), numpy's
error model (a division by zero gives inf/NaN, not an exception), the GIL released (the
node's executor keeps taking messages meanwhile) and numba's on-disk cache (``cache=True``:
``__pycache__`` beside the source when writable, else the user's cache directory, or
``NUMBA_CACHE_DIR``), so that a process loads instead of compiling
(:mod:`photometric.kernel_warm_up`). Where no cache directory is writable the kernel is
compiled in every process, and a warning says how to give it one.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from types import ModuleType

import numba

# Imported for its effect: idle kernel threads sleep (set before numba's first parallel launch).
import fingerps_recon.photometric.kernel_threads  # noqa: F401

_PACKAGE = "fingerps_recon."  # the modules whose kernels may be compiled in
_OPTIONS = {"fastmath": {"contract"}, "error_model": "numpy", "nogil": True}


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


def inlined_modules(kernels: dict[str, object]) -> list[ModuleType]:
    """The modules, other than the one of ``kernels`` (a module's ``globals()``), whose
    functions its kernels may compile in: those of the compiled functions it names, or of
    the project's modules it names (``module.function`` in a kernel), and in turn theirs;
    and this one (the compile options)."""
    own = kernels.get("__name__")
    found: set[str] = set()
    spaces = [kernels]
    while spaces:
        for value in list(spaces.pop().values()):
            if isinstance(value, numba.core.dispatcher.Dispatcher):
                name = getattr(value.py_func, "__module__", own)
            elif isinstance(value, ModuleType) and value.__name__.startswith(_PACKAGE):
                name = value.__name__
            else:
                continue
            if name not in found and name != own and name in sys.modules:
                found.add(name)
                spaces.append(vars(sys.modules[name]))
    return [sys.modules[name] for name in sorted(found | {__name__}) if name in sys.modules]


def drop_stale_caches(kernels: dict[str, object],
                      inlined: Iterable[ModuleType] | None = None) -> int:
    """Delete the on-disk cache of the kernels among ``kernels`` (a module's ``globals()``)
    that is older than a module whose functions they inline or than the compile options
    (``inlined``; by default :func:`inlined_modules`); return how many files.

    Numba keys a kernel's cache to the kernel's own source and bytecode: after an edit of an
    inlined module (e.g. ``symmetric_solve``) or of the options alone, the old machine code
    would be loaded. Called at the import of each kernel module, before any kernel runs (a
    few stat calls)."""
    if inlined is None:
        inlined = inlined_modules(kernels)
    newest = max((Path(module.__file__).stat().st_mtime for module in inlined
                  if module.__file__), default=0.0)
    dropped = 0
    for kernel in kernels.values():
        cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        index = Path(getattr(cache_file, "_index_path", "") or "")
        try:
            stale = index.suffix == ".nbi" and index.stat().st_mtime < newest
        except OSError:  # not cached yet
            continue
        if stale:
            for path in (index, *index.parent.glob(index.name[:-len(".nbi")] + ".*.nbc")):
                path.unlink(missing_ok=True)
                dropped += 1
    return dropped
