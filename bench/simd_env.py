"""The AVX2 run of ``make bench`` on any machine: AVX-512 turned off for every library that
dispatches on it, and what the machine has.

Each library reads its switch once, at import, so the AVX2 run is a process of its own
started with :func:`avx2_env` (``bench/run_all.py``):

- numba (the reconstruction kernels): ``NUMBA_CPU_NAME=haswell`` (the AVX2 + FMA generation:
  its scheduling model) and ``NUMBA_CPU_FEATURES``, the host's own LLVM feature list with
  every AVX-512 feature turned off (``-avx512f``, ``-avx512bw``, ... and ``avx10.*``, which
  implies AVX-512). The feature list is needed: numba takes the host's features whenever
  ``NUMBA_CPU_FEATURES`` is unset, so ``NUMBA_CPU_NAME=haswell`` alone still emits AVX-512
  on an AVX-512 machine. With the host's list every instruction emitted is one the host has,
  Intel or AMD (the CPU name only tunes the schedule). numba caches compiled code per
  (CPU name, features): the AVX2 versions are added to the on-disk cache beside the native
  ones, which stay.
- numpy: ``NPY_DISABLE_CPU_FEATURES``, the dispatched targets of this numpy
  (``__cpu_dispatch__``) that need AVX-512 and this machine has (numpy 2.x: ``X86_V4``,
  ``AVX512_ICL``, ``AVX512_SPR``; 1.x: ``AVX512F``, ``AVX512_SKX``, ...). numpy ignores (with
  an ImportWarning) a name it does not dispatch and refuses to import when one is of its
  baseline, so the list comes from the numpy that runs.
- OpenCV: ``OPENCV_CPU_DISABLE``, OpenCV's own names of the AVX-512 features it knows and
  this machine has (``cv2.getHardwareFeatureName``: ``AVX512F``, ..., ``AVX512-SKX``,
  ``AVX512-COMMON``, ...; ``AVX512_SKX`` with an underscore is unknown to it).

On a machine without AVX-512 the numpy and OpenCV lists are empty (nothing to turn off) and
the AVX2 run differs from the native one only by numba's CPU name.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

NUMBA_AVX2_CPU = "haswell"
SWITCHES = ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES", "NPY_DISABLE_CPU_FEATURES",
            "OPENCV_CPU_DISABLE")
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512cd", "avx512bw",
              "avx512vl", "avx512_vnni", "avx512_bf16", "avx512_fp16")
"""The /proc/cpuinfo flags that say which SIMD code a machine runs (``machine.simd_flags``)."""


def is_avx512(name: str) -> bool:
    """Whether a feature name of LLVM, numpy or OpenCV needs AVX-512 (``avx10.*`` and
    numpy's ``X86_V4`` level imply it)."""
    upper = name.upper()
    return "AVX512" in upper or upper.startswith("AVX10") or upper == "X86_V4"


def numba_features_without_avx512(features: str) -> str:
    """An LLVM feature list (``+avx2,+avx512f,...``) with every AVX-512 feature off."""
    out = []
    for item in filter(None, features.split(",")):
        name = item.lstrip("+-")
        out.append(f"-{name}" if is_avx512(name) else item)
    return ",".join(out)


def host_llvm_features() -> str:
    """The host CPU's LLVM feature list, as numba reads it (``+name`` / ``-name``)."""
    import llvmlite.binding as llvm

    return llvm.get_host_cpu_features().flatten()


def numpy_avx512_targets() -> list[str]:
    """This numpy's dispatched targets that need AVX-512 and this machine has."""
    from numpy._core import _multiarray_umath as umath

    have = umath.__cpu_features__
    return [t for t in umath.__cpu_dispatch__ if is_avx512(t) and have.get(t, False)]


def opencv_avx512_features() -> list[str]:
    """OpenCV's names of the AVX-512 features it knows and this machine has."""
    import cv2

    names = []
    for feature in range(1024):  # OpenCV's CV_HARDWARE_MAX_FEATURE is 512
        name = cv2.getHardwareFeatureName(feature)
        if name and is_avx512(name) and cv2.checkHardwareSupport(feature):
            names.append(name)
    return names


def avx2_switches() -> dict[str, str]:
    """The environment variables that turn AVX-512 off here (see the module docstring).

    Derived from what the machine has, whatever this process was started with: numpy and
    OpenCV report a feature their switch turned off as absent, so in a process that already
    has a switch set (a bench or a test run with AVX-512 off) they are asked in a child
    process started without the switches."""
    if any(name in os.environ for name in SWITCHES[2:]):
        return _switches_of_a_clean_process()
    switches = {"NUMBA_CPU_NAME": NUMBA_AVX2_CPU,
                "NUMBA_CPU_FEATURES": numba_features_without_avx512(host_llvm_features())}
    numpy_targets = numpy_avx512_targets()
    if numpy_targets:
        switches["NPY_DISABLE_CPU_FEATURES"] = ",".join(numpy_targets)
    opencv_features = opencv_avx512_features()
    if opencv_features:
        switches["OPENCV_CPU_DISABLE"] = ",".join(opencv_features)
    return switches


def _switches_of_a_clean_process() -> dict[str, str]:
    """:func:`avx2_switches` computed in a child process without the switches."""
    env = {k: v for k, v in os.environ.items() if k not in SWITCHES}
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import simd_env; "
            "print(json.dumps(simd_env.avx2_switches()))")
    run = subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve().parent)],
                         env=env, capture_output=True, text=True, timeout=300, check=True)
    return json.loads(run.stdout.splitlines()[-1])


def avx2_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default ``os.environ``) with the switches of a native run removed and
    :func:`avx2_switches` set: the environment of the AVX2 run's process."""
    env = {k: v for k, v in (os.environ if base is None else base).items()
           if k not in SWITCHES}
    env.update(avx2_switches())
    return env


def numba_target_has_avx512(env: Mapping[str, str] | None = None) -> bool:
    """Whether numba compiles AVX-512 code in a process with environment ``env`` (default
    ``os.environ``): ``NUMBA_CPU_FEATURES`` if set, else the host's features."""
    env = os.environ if env is None else env
    features = env.get("NUMBA_CPU_FEATURES") or host_llvm_features()
    return "+avx512f" in features.split(",")


def simd_lanes(flags: set[str], env: Mapping[str, str] | None = None) -> int:
    """float32 lanes of the widest SIMD the run's numba kernels use: 16 with AVX-512 (the CPU
    has ``avx512f`` and the run's numba target keeps it), 8 with AVX2, 4 otherwise."""
    if "avx512f" in flags and numba_target_has_avx512(env):
        return 16
    return 8 if "avx2" in flags else 4


def cpu_info(path: str = "/proc/cpuinfo") -> tuple[str, set[str]]:
    """The first CPU's model name and flags from ``/proc/cpuinfo`` (``''``, ``set()`` if
    unreadable)."""
    model, flags = "", set()
    try:
        with open(path) as info:
            for line in info:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and not model:
                    model = value.strip()
                elif key.strip() == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    return model, flags


def machine_figures(switches: Mapping[str, str]) -> dict[str, str | float]:
    """The ``machine.*`` entries of results.json: the CPU's model name and SIMD flags
    (strings), whether the native run had AVX-512 (1 / 0), the cores, and the AVX2 run's
    numpy and OpenCV switches (strings; '' = nothing to turn off)."""
    model, flags = cpu_info()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "machine.cpu_model": model,
        "machine.simd_flags": " ".join(f for f in SIMD_FLAGS if f in flags),
        "machine.native_avx512": float(simd_lanes(flags) == 16),
        "machine.cores": float(cores or 0),
        "machine.avx2_run.numba_cpu": switches.get("NUMBA_CPU_NAME", ""),
        "machine.avx2_run.npy_disable_cpu_features": switches.get("NPY_DISABLE_CPU_FEATURES",
                                                                  ""),
        "machine.avx2_run.opencv_cpu_disable": switches.get("OPENCV_CPU_DISABLE", ""),
    }


def main() -> int:
    """Print the AVX2 run's switches as ``export NAME='value'`` lines, for a shell to
    evaluate (``tools/no_avx512_env.sh``)."""
    for name, value in avx2_switches().items():
        print(f"export {name}='{value}'")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
