"""``upcast bench transfer``: what handing a frame over through a ring costs.

Handoff = from the producer marking the slot READY (its stamp, taken just
before the fence) to the consumer, blocked in another process, holding usable
read-only views. Next to it, in the same run and for the same frames, a plain
memcpy of the frame's bytes into private memory: what any copying transport
(a pipe, a socket, a queue with pickling) would pay at the very least.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from server.frames.frame import Size
from server.frames.ring import DISPLAY_PLANES, RENDER_PLANES, FrameRing, PlaneSpec
from server.frames.timing import Stage
from server.ops.report import BenchReport, summarize_ms


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--frames", type=int, default=600, help="frames per case")
    parser.add_argument("--render-size", default="640x360", help="G-buffer size")
    parser.add_argument("--display-size", default="1280x720", help="output slot size")
    parser.add_argument(
        "--period-ms", type=float, default=4.0, help="producer period (consumer always waits)"
    )


def _producer(name: str, frames: int, width: int, height: int, period_s: float) -> None:
    ring = FrameRing.attach(name, wait_s=5)
    ring.attach_as_producer()
    rng = np.random.default_rng(0)
    for i in range(frames):
        lease = ring.acquire_write(5.0)
        if lease is None:
            continue
        views = lease.views(width, height)
        if i < ring.slot_count:  # give every slot real bytes once; content is irrelevant
            for v in views.values():
                v[...] = rng.integers(0, 255, size=v.shape).astype(v.dtype)
        lease.header["frame_id"] = i
        lease.commit(stamp_stage=Stage.RING_R_READY)
        # Like a game between frames: idle until the next one, so the consumer is
        # blocked in its wait (not polling) when the next commit comes.
        time.sleep(period_s)
    ring.close()


def _measure(
    planes: tuple[PlaneSpec, ...], size: Size, frames: int, period_s: float
) -> dict[str, Any]:
    name = f"upcast-bench-{uuid.uuid4().hex[:10]}"
    ring = FrameRing.create(name, planes, size, slots=3)
    ring.attach_as_consumer()
    nbytes = sum(p.nbytes(size.width, size.height) for p in planes)
    private = {p.name: np.empty(p.shape(size.width, size.height), p.dtype) for p in planes}
    child = mp.get_context("spawn").Process(
        target=_producer, args=(name, frames, size.width, size.height, period_s)
    )
    child.start()
    handoff_ms: list[float] = []
    memcpy_ms: list[float] = []
    try:
        for _ in range(frames):
            lease = ring.acquire_read(10.0)
            if lease is None:
                break
            t_views = time.monotonic_ns()
            ready = int(lease.header["stamps"][Stage.RING_R_READY, 0])
            handoff_ms.append((t_views - ready) / 1e6)
            t0 = time.perf_counter_ns()
            for pname, view in lease.planes.items():
                np.copyto(private[pname], view)
            memcpy_ms.append((time.perf_counter_ns() - t0) / 1e6)
            lease.release()
            if len(handoff_ms) % 100 == 0:
                print(f"  {size} {len(handoff_ms)}/{frames}", file=sys.stderr)
    finally:
        child.join(30)
        ring.close()
        ring.unlink()
    # The first frames include process start-up and page faults: leave them out.
    warm = 10 if len(handoff_ms) > 50 else 0
    handoff = summarize_ms(handoff_ms[warm:])
    memcpy = summarize_ms(memcpy_ms[warm:])
    return {"bytes_per_frame": nbytes, "handoff": handoff, "memcpy": memcpy}


def run(args: argparse.Namespace) -> int:
    cases = [
        ("ring_r_gbuffers", RENDER_PLANES, Size.parse(args.render_size)),
        ("ring_u_display", DISPLAY_PLANES, Size.parse(args.display_size)),
    ]
    report = BenchReport(
        "transfer",
        {
            "frames": args.frames,
            "render_size": args.render_size,
            "display_size": args.display_size,
            "slots": 3,
            "producer_period_ms": args.period_ms,
            "handoff_definition": "producer stamp before READY -> consumer holds read-only views"
            " (cross-process, futex wake)",
        },
    )
    print(f"{'case':18} {'MB':>6} {'handoff p50':>12} {'p95':>8} {'memcpy p50':>11} {'p95':>8}")
    for name, planes, size in cases:
        m = _measure(planes, size, args.frames, args.period_ms / 1000)
        h, c = m["handoff"], m["memcpy"]
        for kind, stats in (("handoff", h), ("memcpy", c)):
            report.add_case(
                f"{name}_{kind}",
                size=str(size),
                bytes_per_frame=m["bytes_per_frame"],
                median_ms=stats["median_ms"],
                p95_ms=stats["p95_ms"],
                stats=stats,
            )
        report.add_ratio(
            f"{name}_handoff_p95_over_memcpy_p95",
            f"{name}_handoff",
            f"{name}_memcpy",
            h["p95_ms"] / c["p95_ms"],
        )
        report.add_ratio(
            f"{name}_handoff_median_over_memcpy_median",
            f"{name}_handoff",
            f"{name}_memcpy",
            h["median_ms"] / c["median_ms"],
        )
        print(
            f"{name:18} {m['bytes_per_frame'] / 1e6:6.2f} {h['median_ms']:12.3f} "
            f"{h['p95_ms']:8.3f} {c['median_ms']:11.3f} {c['p95_ms']:8.3f}"
        )
    report.write(args.json)
    print(f"report written to {args.json}")
    return 0
