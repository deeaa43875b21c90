"""Numba's cache of a kernel is dropped when a module it inlines is newer (kernel_compile)."""

import os
import subprocess
import sys
import types
from pathlib import Path

from fingerps_recon.photometric.kernel_compile import drop_stale_caches


def _kernel_cached_at(index: Path) -> object:
    cache_file = types.SimpleNamespace(_index_path=str(index))
    return types.SimpleNamespace(_cache=types.SimpleNamespace(_cache_file=cache_file))


def test_a_cache_older_than_an_inlined_module_is_dropped_and_a_newer_one_kept(tmp_path):
    old = tmp_path / "kernel.solve-10.py311.nbi"
    new = tmp_path / "kernel.other-20.py311.nbi"
    old_data = [tmp_path / f"kernel.solve-10.py311.{i}.nbc" for i in (1, 2)]
    for path in (old, new, *old_data, tmp_path / "kernel.other-20.py311.1.nbc"):
        path.write_bytes(b"x")
    inlined = tmp_path / "inlined.py"
    inlined.write_text("")
    os.utime(old, (1000, 1000))
    os.utime(inlined, (2000, 2000))
    os.utime(new, (3000, 3000))
    module = types.ModuleType("inlined")
    module.__file__ = str(inlined)
    kernels = {"solve": _kernel_cached_at(old), "other": _kernel_cached_at(new),
               "not_a_kernel": 3, "uncached": _kernel_cached_at(tmp_path / "none.nbi")}

    assert drop_stale_caches(kernels, inlined=(module,)) == 3
    assert not old.exists() and not any(p.exists() for p in old_data)
    assert new.exists() and (tmp_path / "kernel.other-20.py311.1.nbc").exists()
    assert drop_stale_caches(kernels, inlined=(module,)) == 0


def test_the_kernels_recompile_after_an_edit_of_symmetric_solve(tmp_path):
    """Real numba: kernels cached under NUMBA_CACHE_DIR, then symmetric_solve made newer
    (as an edit would): the next process drops those caches and compiles again."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    # Prints what the import dropped, whether an index in argv survived it, then calls the
    # jitted adjugate: its determinant and the dispatcher's cache hits and misses.
    run = ("import os, sys\n"
           "import numpy as np\n"
           "from fingerps_recon.photometric import lambertian_kernel as k, symmetric_solve\n"
           "print(k.drop_stale_caches(vars(k), inlined=(symmetric_solve,)))\n"
           "print(any(os.path.exists(index) for index in sys.argv[1:]))\n"
           "m = np.float32\n"
           "print(k._adjugate(m(2), m(0), m(0), m(2), m(0), m(2))[6])\n"
           "stats = k._adjugate.stats\n"
           "print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))\n")
    # Compile the jitted adjugate into the cache, then age the cache below the source.
    warm = subprocess.run([sys.executable, "-c", run], env=env, check=True,
                          capture_output=True, text=True).stdout.split()
    assert warm == ["0", "False", "8.0", "0", "1"]  # compiled: a cache miss
    indexes = list((tmp_path / "cache").rglob("*.nbi"))
    assert indexes, "numba wrote no cache"
    for index in indexes:
        os.utime(index, (1000, 1000))
    out = subprocess.run([sys.executable, "-c", run, *map(str, indexes)], env=env,
                         check=True, capture_output=True, text=True).stdout.split()
    # The module's import already dropped them (its own call then finds none left) ...
    assert out[0] == "0"
    assert out[1] == "False"
    # ... so the adjugate compiled again (a miss, not a hit of the stale code) and was
    # cached anew.
    assert out[2:] == ["8.0", "0", "1"]
    assert all(index.stat().st_mtime > 1000 for index in indexes)


def test_the_modules_a_kernel_module_inlines_are_found_from_its_kernels():
    from fingerps_recon.photometric import (
        hk_gather_kernel,
        hk_model_kernel,
        hk_passes_kernel,
        hk_step_kernel,
        kernel_compile,
        lambertian_kernel,
        normal_transform_kernel,
        symmetric_solve,
    )
    from fingerps_recon.photometric.kernel_compile import inlined_modules

    # The compile options count as inlined too: an edit of them recompiles every kernel.
    assert inlined_modules(vars(lambertian_kernel)) == [kernel_compile, symmetric_solve]
    assert inlined_modules(vars(normal_transform_kernel)) == [kernel_compile]
    assert inlined_modules(vars(hk_model_kernel)) == [kernel_compile]
    assert inlined_modules(vars(hk_gather_kernel)) == [hk_model_kernel, kernel_compile]
    assert inlined_modules(vars(hk_step_kernel)) == [hk_model_kernel, kernel_compile,
                                                     symmetric_solve]
    # The passes' caches follow also what the step helpers they call (hk_step_kernel.steps)
    # inline, through the module they name.
    assert inlined_modules(vars(hk_passes_kernel)) == [hk_gather_kernel, hk_model_kernel,
                                                       hk_step_kernel, kernel_compile,
                                                       symmetric_solve]
