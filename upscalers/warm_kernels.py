"""Compile every numba CPU kernel once, so the first frame of a stream does not.

numba compiles a kernel on its first call and keeps the machine code in its
on-disk cache (``__pycache__`` beside the source, or numba's user cache where
that is read-only). A cold compile of the FSR 1, temporal and MPE kernels takes
about two minutes on a 2-core machine (108 s measured); a worker that met it on
its first frame would freeze the stream that long. ``./dev`` runs this after
installing, the session image at build time; afterwards a worker loads the
kernels in under a second.

Kernels are compiled per argument type, not per size: tiny frames of each kind
the pipeline passes (read-only ring views and writable arrays; integer and other
scales) are enough.

    python -m upscalers.warm_kernels
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from server.frame import Camera, FrameMeta, RenderFrame, Size
from upscalers.fsr1 import EasuRcasUpscaler, EasuUpscaler
from upscalers.temporal import TemporalUpscaler

_RENDER = Size(24, 14)
_DISPLAYS = (Size(48, 28), Size(36, 21))  # 2x (integer-scale kernels), 1.5x (the others)


def _frame(read_only: bool) -> RenderFrame:
    w, h = _RENDER
    rng = np.random.default_rng(0)
    frame = RenderFrame(
        color=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=np.full((h, w), 0.9, np.float32),
        motion=np.full((h, w, 2), 0.25, np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(frame_id=0, camera=Camera.identity()),
    )
    if read_only:  # what the worker gets: views of a ring slot
        for plane in (frame.color, frame.depth, frame.motion, frame.dynamic_mask):
            plane.setflags(write=False)
    return frame


def warm_up() -> float:
    """Run every CPU kernel on tiny frames; seconds spent (compiling or loading)."""
    from upscalers.framegen import MpeOptions
    from upscalers.framegen.mpe_cpu import warm_up as warm_up_mpe

    t0 = time.perf_counter()
    for read_only in (True, False):
        frame = _frame(read_only)
        for display in _DISPLAYS:
            for fsr in (EasuUpscaler(), EasuRcasUpscaler()):
                fsr.upscale(frame, display)
            temporal = TemporalUpscaler(device="cpu")
            for _ in range(2):  # the second frame fetches history
                temporal.upscale(frame, display)
    warm_up_mpe(MpeOptions())
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m upscalers.warm_kernels",
        description="Compile the numba CPU kernels (FSR 1, temporal, MPE) into numba's cache.",
    )
    parser.parse_args(argv)
    print(
        "compiling the CPU kernels (numba; about two minutes the first time) ...", file=sys.stderr
    )
    took = warm_up()
    print(f"CPU kernels ready in {took:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
