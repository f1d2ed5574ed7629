"""Compile every numba CPU kernel once, so the first frame of a stream does not.

numba compiles a kernel on its first call and keeps the machine code in its
on-disk cache (``__pycache__`` beside the source, or numba's user cache where
that is read-only). A cold compile of the FSR 1, temporal and MPE kernels takes
about two minutes on a 2-core machine one family after another (108 s measured);
a worker that met it on its first frame would freeze the stream that long.
``./dev test`` runs this after installing, ``./dev up`` in the background (see
``kernel_readiness``), the session image at build time; afterwards a worker
loads the kernels in under a second.

Kernels are compiled per argument type, not per size: tiny frames of each kind
the pipeline passes (read-only ring views and writable arrays; integer and other
scales) are enough.

The three kernel families live in separate source files (separate cache files), and
numba compiles on one thread, so they compile in parallel processes, one per core
(``--jobs``): on a fresh 2-core clone, 83 s for all three beside a starting stack
(temporal 79 s, MPE 44 s, FSR 1 35 s).

    python -m upscalers.kernels.warm [--jobs N]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from upscalers.fsr1.upscaler import EasuRcasUpscaler, EasuUpscaler
from upscalers.temporal.upscaler import TemporalUpscaler

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


def _warm_fsr1() -> None:
    for read_only in (True, False):
        frame = _frame(read_only)
        for display in _DISPLAYS:
            for fsr in (EasuUpscaler(backend="numba"), EasuRcasUpscaler(backend="numba")):
                fsr.upscale(frame, display)


def _warm_temporal() -> None:
    for read_only in (True, False):
        frame = _frame(read_only)
        for display in _DISPLAYS:
            temporal = TemporalUpscaler(device="cpu", backend="numba")
            for _ in range(2):  # the second frame fetches history
                temporal.upscale(frame, display)
            # Area samples (photographs, video) take the preconditioned back-projection.
            area = replace(frame, meta=replace(frame.meta, flags=FrameFlags.AREA_SAMPLES))
            temporal.upscale(area, display)


def _warm_mpe() -> None:
    from upscalers.framegen import MpeOptions
    from upscalers.framegen.mpe_cpu import warm_up as warm_up_mpe

    warm_up_mpe(MpeOptions(backend="numba"))


# The largest family first, so that with fewer cores than families it starts at once.
FAMILIES: dict[str, Callable[[], None]] = {
    "temporal": _warm_temporal,
    "FSR 1": _warm_fsr1,
    "MPE": _warm_mpe,
}


def _timed(name: str) -> float:
    t0 = time.perf_counter()
    FAMILIES[name]()
    return time.perf_counter() - t0


def warm_up(jobs: int = 1) -> float:
    """Run every CPU kernel on tiny frames (in ``jobs`` processes when above 1);
    seconds spent (compiling or loading)."""
    t0 = time.perf_counter()
    if jobs <= 1:
        for name in FAMILIES:
            _timed(name)
        return time.perf_counter() - t0
    # spawn: a forked child would inherit torch's and numba's thread pools mid-state.
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        futures = {name: pool.submit(_timed, name) for name in FAMILIES}
        for name, future in futures.items():
            print(f"  {name} kernels ready in {future.result():.1f} s", file=sys.stderr)
    return time.perf_counter() - t0


def default_jobs() -> int:
    return max(1, min(len(FAMILIES), os.cpu_count() or 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m upscalers.kernels.warm",
        description="Compile the numba CPU kernels (FSR 1, temporal, MPE) into numba's cache.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=default_jobs(),
        help="processes compiling at once (1: in this process); one per core up to "
        f"{len(FAMILIES)} kernel families",
    )
    args = parser.parse_args(argv)
    print(
        f"compiling the CPU kernels (numba, {max(1, args.jobs)} at once; about 90 s on "
        "2 cores the first time, under a few seconds from the cache) ...",
        file=sys.stderr,
    )
    took = warm_up(args.jobs)
    print(f"CPU kernels ready in {took:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
