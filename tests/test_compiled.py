"""The opt-in compiled path (torch.compile, inductor C++) gives the eager results.

Each geometry compiles once (tens of seconds cold on 2 cores), so one small
geometry: EASU+RCAS at a non-integer scale with odd sizes (edge clamps,
gathered taps); EASU alone is the same function without RCAS.
"""

from __future__ import annotations

import numpy as np
import pytest

from server.frames.frame import Size
from tests.test_fsr1 import make_frame
from upscalers import registry
from upscalers.fsr1.upscaler import EasuRcasUpscaler
from upscalers.host import UpscalerHost

pytestmark = pytest.mark.slow


def test_easu_rcas_compiled_matches_eager() -> None:
    rng = np.random.default_rng(3)
    render, display = Size(21, 13), Size(32, 20)  # 1.5x-ish, odd: gathered taps, edge clamps
    frames = [rng.integers(0, 256, (render.height, render.width, 3), dtype=np.uint8)]
    frames.append(np.zeros_like(frames[0]))  # black: EASU's 0/0 guards
    eager = EasuRcasUpscaler(sharpness=0.5, backend="torch")
    compiled = EasuRcasUpscaler(0.5, compile=True)
    for color in frames:
        frame = make_frame(color)
        a, b = eager.upscale(frame, display), compiled.upscale(frame, display)
        # float32, same operations in another order: well under one 8-bit step.
        assert (a - b).abs().max() < 1e-4
    assert compiled.compiled is not None and list(compiled.compiled.warmup_s) == ["3x17x25"]


def test_compile_is_an_upscaler_option() -> None:
    host = UpscalerHost("easu", Size(32, 18), {"compile": True})
    assert host.upscaler.compiled is not None  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="no option compile"):
        registry.create("bicubic", compile=True)
    assert not registry.takes_option("temporal", "compile")  # measured no faster: none


def test_worker_compile_flag_reaches_the_host() -> None:
    host = UpscalerHost("bilinear", Size(32, 18), compile=True)
    assert not registry.takes_option("bilinear", "compile")
    host.switch("easu_rcas")  # a method with a compiled path gets it after a switch too
    assert host.upscaler.compiled is not None  # type: ignore[attr-defined]
