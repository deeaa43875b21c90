# Source this (bash) to run tests or benchmarks as on an AVX2 machine: AVX-512 off for every
# library here that dispatches on it (numba, numpy, OpenCV, OpenBLAS). CONVENTIONS.md says
# how to check that each switch is honoured. numba's cache keeps kernels per target: run
# `python -m fingerps_recon.photometric.kernel_warm_up` once in this environment.
# shellcheck shell=bash
# numba: the name alone keeps the host's features, so the features go with it
export NUMBA_CPU_NAME=haswell
export NUMBA_CPU_FEATURES="+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+cx8,+f16c,+fma,+fxsr,+lzcnt,+mmx,+movbe,+popcnt,+sahf,+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3,+xsave,-avx512f"
# numpy 2.4 dispatches these groups (it ignores single features such as AVX512F)
export NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"
export OPENCV_CPU_DISABLE="AVX512F,AVX512BW,AVX512CD,AVX512DQ,AVX512VL,AVX512-SKX,AVX512-COMMON,AVX512-ICL,AVX512-CNL,AVX512-CLX"
export OPENBLAS_CORETYPE=Haswell
