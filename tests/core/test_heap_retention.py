"""Freed memory stays in the process between bursts (fingerps_recon.heap_retention).

Each case runs in a process of its own (malloc's thresholds are per process): it writes
100 MB of 5 MB arrays, frees them, does it again three times, and reports the page faults
of those three rounds. glibc's defaults give most of it back to the kernel and fault it in
again each round; with the thresholds that importing the pipeline sets, the rounds reuse it.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

PROBE = r"""
import json, resource, sys
import numpy as np
if sys.argv[1] == "pipeline":
    import fingerps_recon.photometric.pipeline  # noqa: F401  (sets the thresholds)

def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

def burst():
    arrays = [np.ones(5 << 20, np.uint8) for _ in range(20)]
    del arrays

burst()
start = faults()
for _ in range(3):
    burst()
print(json.dumps({"faults_per_round": (faults() - start) / 3}))
"""

# 100 MB in 4 KiB pages (fewer with transparent huge pages).
_PAGES = (100 << 20) // 4096


def _faults(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["faults_per_round"]


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the thresholds are glibc's")
def test_importing_the_pipeline_keeps_freed_memory_for_the_next_burst() -> None:
    kept = _faults("pipeline")
    assert kept < 0.01 * _PAGES, kept
    # The probe measures something: with glibc's defaults the same rounds fault.
    assert _faults("default") > 0.1 * _PAGES


def test_retain_freed_memory_says_whether_it_applied() -> None:
    from fingerps_recon.heap_retention import retain_freed_memory

    assert retain_freed_memory() is (platform.libc_ver()[0] == "glibc")
