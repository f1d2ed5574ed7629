"""``upcast bench pipeline``: game -> ring R -> worker -> ring U, as separate processes.

The benchmark process is ring U's consumer (where the encoder will sit). It
reads every display frame's stamps and reports the rate it received frames
at, the frames lost anywhere on the way, and each stage's latency.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from server.bench.report import BenchReport, summarize_ms
from server.stack import LocalStack, SessionConfig
from server.timing import STAGE_SPANS, Stage


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds measured")
    parser.add_argument("--warmup", type=float, default=3.0, help="seconds before measuring")
    parser.add_argument("--scene", default="default")
    parser.add_argument("--render-size", default="640x360")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--upscaler", default="bilinear")
    parser.add_argument("--game-threads", type=int, default=1, help="torch threads, game")
    parser.add_argument("--worker-threads", type=int, default=1, help="torch threads, worker")


def run(args: argparse.Namespace) -> int:
    config = SessionConfig(
        scene=args.scene,
        render_size=args.render_size,
        display_size=args.display_size,
        fps=args.fps,
        upscaler=args.upscaler,
        game_threads=args.game_threads,
        worker_threads=args.worker_threads,
    )
    total = args.warmup + args.duration
    stack = LocalStack(config, game_duration_s=total + 2.0)
    stamps: list[np.ndarray] = []
    frame_ids: list[int] = []
    received_ns: list[int] = []
    with stack:
        stack.wait_ready()
        ring_u = stack.ring_u
        assert ring_u is not None
        ring_u.attach_as_consumer()
        start = time.monotonic()
        measure_from = start + args.warmup
        next_progress = measure_from
        base_r = base_u = None
        while time.monotonic() - start < total:
            lease = ring_u.acquire_read(0.5)
            now = time.monotonic()
            if base_r is None and now >= measure_from:
                assert stack.ring_r is not None
                base_r, base_u = stack.ring_r.counters(), ring_u.counters()
            if lease is None:
                stack.check_children()
                continue
            with lease:
                record = np.array(lease.header["stamps"], dtype=np.int64)
                record[Stage.ENCODE_START] = (time.monotonic_ns(), time.time_ns())
                frame_id = int(lease.header["frame_id"])
            if now >= measure_from:
                stamps.append(record)
                frame_ids.append(frame_id)
                received_ns.append(int(record[Stage.ENCODE_START, 0]))
            if now >= next_progress:
                print(
                    f"  {now - measure_from:5.1f}/{args.duration:.0f} s  frames {len(frame_ids)}",
                    file=sys.stderr,
                )
                next_progress += 5.0
        assert stack.ring_r is not None and base_r is not None and base_u is not None
        end_r, end_u = stack.ring_r.counters(), ring_u.counters()
        restarts = stack.worker_restarts
    result = _summarize(stamps, frame_ids, received_ns)
    dropped_r = end_r.dropped - base_r.dropped
    dropped_u = end_u.dropped - base_u.dropped
    report = BenchReport("pipeline", {**config.model_dump(), "duration_s": args.duration})
    report.add_case(
        "pipeline",
        achieved_fps=result["fps"],
        target_fps=args.fps,
        frames_received=len(frame_ids),
        frames_missing_by_id=result["missing_ids"],
        ring_r_dropped=dropped_r,
        ring_u_dropped=dropped_u,
        worker_restarts=restarts,
        median_ms=result["stages"]["render_start_to_ring_u_consumer"].get("median_ms"),
        p95_ms=result["stages"]["render_start_to_ring_u_consumer"].get("p95_ms"),
        stages=result["stages"],
    )
    report.write(args.json)
    print(
        f"fps {result['fps']:.2f} (target {args.fps:g}), frames {len(frame_ids)}, "
        f"missing ids {result['missing_ids']}, dropped ring R {dropped_r} ring U {dropped_u}"
    )
    print(f"{'stage':34} {'p50 ms':>8} {'p95 ms':>8}")
    for name, s in result["stages"].items():
        if s.get("count"):
            print(f"{name:34} {s['median_ms']:8.3f} {s['p95_ms']:8.3f}")
    print(f"report written to {args.json}")
    return 0


def _summarize(
    stamps: list[np.ndarray], frame_ids: list[int], received_ns: list[int]
) -> dict[str, Any]:
    stages: dict[str, dict[str, float]] = {}
    if not stamps:
        return {"fps": 0.0, "missing_ids": 0, "stages": {"render_start_to_ring_u_consumer": {}}}
    arr = np.stack(stamps)  # (N, STAGE_COUNT, 2)
    mono = arr[:, :, 0]
    spans = [s for s in STAGE_SPANS if s[2] <= Stage.ENCODE_START]
    for name, a, b in spans:
        ok = (mono[:, a] > 0) & (mono[:, b] > 0)
        if ok.any():
            stages[name] = summarize_ms((mono[ok, b] - mono[ok, a]) / 1e6)
    stages["render_start_to_ring_u_consumer"] = summarize_ms(
        (mono[:, Stage.ENCODE_START] - mono[:, Stage.RENDER_START]) / 1e6
    )
    duration_s = (received_ns[-1] - received_ns[0]) / 1e9
    fps = (len(received_ns) - 1) / duration_s if duration_s > 0 else 0.0
    ids = np.asarray(frame_ids)
    missing = int((ids[-1] - ids[0] + 1) - len(np.unique(ids)))
    return {"fps": fps, "missing_ids": missing, "stages": stages}
