"""While ``./dev up`` compiles the numba kernels in the background (UPCAST_KERNELS_MARKER
names a file not yet written), backend "auto" runs torch, saying so once; once the file
exists, a new upscaler takes the kernels. Explicit backends are unaffected."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from server.frames.frame import Size
from upscalers.framegen.mpe import MeshProjectionPredictor
from upscalers.fsr1.upscaler import EasuRcasUpscaler, EasuUpscaler
from upscalers.kernels import readiness as kernel_readiness
from upscalers.kernels.readiness import ENV_VAR, kernels_ready
from upscalers.kernels.warm import _frame
from upscalers.temporal.upscaler import TemporalUpscaler


@pytest.fixture
def marker(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    path = tmp_path / ".kernels-warm"
    monkeypatch.setenv(ENV_VAR, str(path))
    monkeypatch.setattr(kernel_readiness, "_told", set())
    return path


def _temporal_uses_numba() -> bool:
    temporal = TemporalUpscaler(device="cpu")
    temporal.upscale(_frame(read_only=True), Size(48, 28))
    return temporal._host is not None


def test_auto_runs_torch_until_the_marker_exists(
    marker: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger=kernel_readiness.__name__):
        assert EasuUpscaler().backend == "torch"
        assert EasuRcasUpscaler().backend == "torch"
        assert EasuUpscaler().backend == "torch"
        assert not _temporal_uses_numba()
        assert MeshProjectionPredictor().backend == "torch"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines  # one per method, not one per upscaler
    assert all("still compiling" in line for line in lines)
    # An explicit choice is honoured (the tests and warm_kernels compile on purpose).
    assert EasuUpscaler(backend="numba").backend == "numba"

    marker.touch()
    assert EasuUpscaler().backend == "numba"
    assert _temporal_uses_numba()
    assert MeshProjectionPredictor().backend == "numba"


def test_without_the_variable_the_kernels_count_as_ready(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert kernels_ready("FSR 1")
    assert EasuUpscaler().backend == "numba"
