"""photometric.kernel_warm_up: every kernel the pipeline calls is ready afterwards."""

from __future__ import annotations

from fingerps_recon.photometric import kernel_warm_up
from fingerps_recon.photometric.kernel_warm_up import KERNEL_MODULES, WarmUp, warm_up_kernels


def test_warm_up_readies_every_kernel_and_a_second_call_compiles_nothing() -> None:
    first = warm_up_kernels()
    assert isinstance(first, WarmUp) and first.modules == KERNEL_MODULES
    assert first.compiled + first.loaded > 0  # kernel versions compiled or loaded so far
    second = warm_up_kernels()
    assert second.compiled == first.compiled  # nothing new to compile: the same signatures
    assert second.loaded == first.loaded  # nor to load: every version is in memory already
    assert first.summary.startswith("compiled" if first.compiled else "loaded")
    assert second.summary.startswith(("loaded", "compiled"))


def test_the_build_step_prints_one_line(capsys) -> None:
    assert kernel_warm_up.main([]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fingerps_recon kernels: ")
