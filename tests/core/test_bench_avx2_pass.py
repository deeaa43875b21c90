"""make bench's AVX2 pass (bench/simd_env.py, bench/run_all.py), without timing anything:
the environment it builds turns off exactly the AVX-512 features this machine's numba, numpy
and OpenCV would use (checked in a process started with it), and the two passes' figures
merge into results.json as ``<name>.avx2`` beside the native names."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
from numpy._core import _multiarray_umath as umath

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))

import run_all  # noqa: E402
import simd_env  # noqa: E402

_, FLAGS = simd_env.cpu_info()

# Run in a process started with the AVX2 environment: what each library then uses.
PROBE = r"""
import json, re
import numba, numpy as np, cv2
from numpy._core import _multiarray_umath as umath

@numba.njit(fastmath=True)
def dot_exp(a, b):
    s = np.float32(0)
    for i in range(a.size):
        s += a[i] * b[i] + np.exp(a[i])
    return s

a = np.ones(4096, np.float32)
dot_exp(a, a)
asm = dot_exp.inspect_asm(dot_exp.signatures[0])
names = {i: cv2.getHardwareFeatureName(i) for i in range(1024)}
print(json.dumps({
    "zmm": len(re.findall(r"%zmm\d", asm)),
    "ymm": len(re.findall(r"%ymm\d", asm)),
    "numpy": {k: bool(v) for k, v in umath.__cpu_features__.items()},
    "opencv": {n: bool(cv2.checkHardwareSupport(i)) for i, n in names.items() if n},
}))
"""


@pytest.fixture(scope="module")
def avx2_env() -> dict[str, str]:
    return simd_env.avx2_env()


def _probe(env: dict[str, str]) -> tuple[dict, str]:
    run = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.splitlines()[-1]), run.stderr


@pytest.fixture(scope="module")
def probed(avx2_env) -> tuple[dict, str]:
    return _probe(avx2_env)


@pytest.fixture(scope="module")
def machine() -> dict:
    """What numpy and OpenCV find on this machine, asked in a process without the switches
    (this one may run with AVX-512 off: then they report those features absent)."""
    return _probe({k: v for k, v in os.environ.items() if k not in simd_env.SWITCHES})[0]


def test_numba_gets_the_hosts_features_with_exactly_the_avx512_ones_off(avx2_env):
    assert avx2_env["NUMBA_CPU_NAME"] == "haswell"
    host = simd_env.host_llvm_features().split(",")
    avx2 = avx2_env["NUMBA_CPU_FEATURES"].split(",")
    assert [f.lstrip("+-") for f in avx2] == [f.lstrip("+-") for f in host]
    changed = {h.lstrip("+-") for h, a in zip(host, avx2, strict=True) if h != a}
    assert changed == {h[1:] for h in host if h.startswith("+") and simd_env.is_avx512(h[1:])}
    assert not [f for f in avx2 if f.startswith("+") and simd_env.is_avx512(f[1:])]
    assert simd_env.numba_target_has_avx512(avx2_env) is False


def test_numpy_is_told_exactly_its_dispatched_avx512_targets_this_machine_has(avx2_env,
                                                                            machine):
    expected = [t for t in umath.__cpu_dispatch__
                if simd_env.is_avx512(t) and machine["numpy"].get(t)]
    assert avx2_env.get("NPY_DISABLE_CPU_FEATURES", "").split(",") == (expected or [""])
    assert all(t in umath.__cpu_dispatch__ for t in expected)  # else numpy ignores it


def test_opencv_is_told_exactly_its_avx512_features_this_machine_has(avx2_env, machine):
    expected = [n for i in range(1024) if (n := cv2.getHardwareFeatureName(i))
                and "AVX512" in n and machine["opencv"].get(n)]
    assert avx2_env.get("OPENCV_CPU_DISABLE", "").split(",") == (expected or [""])


def test_in_the_avx2_process_no_library_uses_avx512(probed):
    figures, stderr = probed
    assert figures["zmm"] == 0  # numba emitted no 512-bit register
    if "avx2" in FLAGS:
        assert figures["ymm"] > 0  # ... and still vectorised with AVX2
        assert figures["numpy"]["AVX2"] and figures["opencv"]["AVX2"]
    assert not [t for t in umath.__cpu_dispatch__
                if simd_env.is_avx512(t) and figures["numpy"][t]]
    assert not [n for n, on in figures["opencv"].items() if "AVX512" in n and on]
    # every name was understood: no "unknown CPU feature" (OpenCV) nor ignored name (numpy)
    assert "OPENCV: Trying to disable" not in stderr
    assert "NPY_DISABLE_CPU_FEATURES" not in stderr


def test_a_process_already_without_avx512_derives_the_same_switches(avx2_env):
    """A bench or test started with AVX-512 already off (numpy and OpenCV then report those
    features absent) still gives its AVX2 child process the machine's whole list."""
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import simd_env; "
            "print(json.dumps(simd_env.avx2_switches()))")
    run = subprocess.run([sys.executable, "-c", code, str(BENCH)], env=avx2_env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    nested = json.loads(run.stdout.splitlines()[-1])
    assert nested == {k: v for k, v in avx2_env.items() if k in simd_env.SWITCHES}


def test_a_users_switch_does_not_leak_into_the_avx2_run():
    env = simd_env.avx2_env({"PATH": "/bin", "NUMBA_CPU_NAME": "skylake-avx512",
                             "OPENCV_CPU_DISABLE": "AVX2", "NPY_DISABLE_CPU_FEATURES": "X86_V3"})
    assert env["PATH"] == "/bin" and env["NUMBA_CPU_NAME"] == "haswell"
    assert "AVX2" not in env.get("OPENCV_CPU_DISABLE", "").split(",")
    assert "X86_V3" not in env.get("NPY_DISABLE_CPU_FEATURES", "").split(",")


def test_the_feature_list_arithmetic():
    assert simd_env.numba_features_without_avx512(
        "+avx2,+avx512f,-avx512fp16,+avx10.1,+fma,+amx-avx512,-sse4a") == \
        "+avx2,-avx512f,-avx512fp16,-avx10.1,+fma,-amx-avx512,-sse4a"
    assert [simd_env.is_avx512(n) for n in ("X86_V4", "X86_V3", "AVX512-SKX", "AVX2")] == \
        [True, False, True, False]


def test_the_peak_is_the_avx2_one_in_the_avx2_run(avx2_env):
    import bench_recon_speed

    if "avx2" not in FLAGS:
        pytest.skip("no AVX2 on this machine")
    native, _ = bench_recon_speed.peak_gflops({})
    avx2, avx2_how = bench_recon_speed.peak_gflops(avx2_env)
    assert "x 8 float32 lanes" in avx2_how
    assert simd_env.simd_lanes(FLAGS, avx2_env) == 8
    assert native == pytest.approx(avx2 * (2 if "avx512f" in FLAGS else 1))


def test_the_two_passes_merge_into_avx2_names_beside_the_native_ones():
    native = {"recon.ms.pipeline_hk": 60.0, "recon.um.depth_rms_ortho_fast": 3.0,
              "e2e.hk.lost": 0.0}
    avx2 = {"recon.ms.pipeline_hk": 90.0, "e2e.hk.lost": 1.0}
    machine = simd_env.machine_figures(simd_env.avx2_switches())
    merged = run_all.merge({"soak.bursts_lost": 0.0}, native, avx2, machine)
    assert merged["recon.ms.pipeline_hk"] == 60.0 and merged["recon.ms.pipeline_hk.avx2"] == 90.0
    assert merged["e2e.hk.lost.avx2"] == 1.0 and merged["soak.bursts_lost"] == 0.0
    assert "recon.um.depth_rms_ortho_fast.avx2" not in merged
    assert isinstance(merged["machine.cpu_model"], str)
    # whether the native pass (this process: maybe started with AVX-512 off) used AVX-512
    assert merged["machine.native_avx512"] == float(
        "avx512f" in FLAGS and simd_env.numba_target_has_avx512())
    assert set(merged["machine.simd_flags"].split()) <= FLAGS
    assert json.loads(json.dumps(merged, allow_nan=False)) == merged


def test_the_avx2_pass_keeps_speed_figures_only():
    def speed(bench: str, name: str) -> bool:
        return run_all.SPEED[bench][1](name)

    assert set(run_all.SPEED) == {"bench_driver", "bench_driver_publish", "bench_recon_speed",
                                  "bench_recon_publish", "bench_e2e", "bench_fingerprint"}
    assert speed("bench_recon_speed", "recon.ms.pipeline_hk")
    assert speed("bench_recon_speed", "recon.hk_kernel.peak_gflops")
    assert not speed("bench_recon_speed", "recon.um.depth_rms_ortho_fast")
    assert not speed("bench_e2e", "e2e.mae_deg") and speed("bench_e2e", "e2e.hk.lost")
    assert speed("bench_fingerprint", "fingerprint.hk.print_ms_median")
    assert not speed("bench_fingerprint", "fingerprint.hk.recall")
