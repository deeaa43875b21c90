# Source this (bash), after tools/ros_env.sh, to run tests or benchmarks as on an AVX2
# machine: AVX-512 off for numba, numpy and OpenCV, with the switches make bench's AVX2
# pass uses (bench/simd_env.py, one definition). CONVENTIONS.md says how to check that each
# is honoured. numba's cache keeps kernels per target: run
# `python -m fingerps_recon.photometric.kernel_warm_up` once in this environment.
# shellcheck shell=bash
eval "$(python "$(dirname "${BASH_SOURCE[0]}")/../bench/simd_env.py")"
