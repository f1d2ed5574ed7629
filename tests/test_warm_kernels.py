"""``python -m upscalers.kernels.warm``: every CPU kernel a stream needs is compiled (or
loaded from numba's cache) before the first frame, for ring views and plain arrays."""

from __future__ import annotations

import pytest

from upscalers.fsr1 import cpu_kernels as fsr1_cpu_kernels
from upscalers.kernels.warm import main
from upscalers.temporal import cpu_kernels as temporal_cpu_kernels


def test_warm_up_compiles_the_kernels_a_worker_calls(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--jobs", "1"]) == 0  # in this process, so its signatures show here
    assert "CPU kernels ready" in capsys.readouterr().err
    # Both integer-scale and other-scale EASU, for read-only ring views and writable arrays.
    assert fsr1_cpu_kernels.easu_integer.signatures
    assert fsr1_cpu_kernels.easu_gathered.signatures
    colour_types = {sig[0] for sig in fsr1_cpu_kernels.pad_and_fields.signatures}
    assert {t.mutable for t in colour_types} == {True, False}
    for name in ("display_blocked", "display_generic"):
        assert getattr(temporal_cpu_kernels, name).signatures, name


def test_the_kernel_families_compile_in_parallel_processes(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--jobs", "2"]) == 0
    err = capsys.readouterr().err
    assert "2 at once" in err
    for family in ("temporal", "FSR 1", "MPE"):
        assert f"{family} kernels ready in" in err
    assert "CPU kernels ready" in err
