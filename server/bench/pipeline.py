"""``upcast bench pipeline``: game -> ring R -> worker -> ring U, as separate processes.

The benchmark process is ring U's consumer (where the encoder will sit). It
reads every display frame's stamps and reports the rate it received frames
at, the frames lost anywhere on the way, and each stage's latency.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

from server.frames.frame import FrameFlags
from server.frames.ring import FrameRing
from server.frames.timing import STAGE_COUNT, STAGE_SPANS, Stage
from server.ops.report import BenchReport, summarize_ms
from server.stack.local import LocalStack, SessionConfig


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
    parser.add_argument(
        "--worker-threads", type=int, default=1, help="CPU threads of the worker (torch and numba)"
    )
    parser.add_argument(
        "--frame-generation",
        choices=("off", "on", "both"),
        default="off",
        help="predict every other frame; both: compare, without prediction at fps/2 (the same "
        "render rate) and with it at fps (default: off)",
    )


def run(args: argparse.Namespace) -> int:
    modes = {"off": [False], "on": [True], "both": [False, True]}[args.frame_generation]
    report: BenchReport | None = None
    results: dict[bool, dict[str, Any]] = {}
    for frame_generation in modes:
        # "both" compares at one render rate: without prediction the game renders at
        # fps / 2 and presents that; with it, it renders fps / 2 and presents fps.
        fps = args.fps / 2 if args.frame_generation == "both" and not frame_generation else args.fps
        config = SessionConfig(
            scene=args.scene,
            render_size=args.render_size,
            display_size=args.display_size,
            fps=fps,
            upscaler=args.upscaler,
            frame_generation=frame_generation,
            game_threads=args.game_threads,
            worker_threads=args.worker_threads,
        )
        label = "frame generation on" if frame_generation else "frame generation off"
        print(f"{label}: {config.fps:g} fps for {args.duration:g} s", file=sys.stderr)
        case = _measure(config, args)
        results[frame_generation] = case
        if report is None:
            report = BenchReport(
                "pipeline",
                {
                    **config.model_dump(exclude={"fps", "frame_generation"}),
                    "duration_s": args.duration,
                    "fps": args.fps,
                    "frame_generation": args.frame_generation,
                },
            )
        name = "framegen_on" if frame_generation else "framegen_off"
        report.add_case(name, target_fps=config.fps, frame_generation=frame_generation, **case)
        _print_case(name, case, config.fps)
    assert report is not None
    if len(results) == 2:
        off, on = results[False], results[True]
        report.add_ratio(
            "presented fps, frame generation on / off", "framegen_on", "framegen_off",
            on["achieved_fps"] / off["achieved_fps"] if off["achieved_fps"] else float("nan"),
        )  # fmt: skip
        report.notes.append(
            "framegen_off runs the game at fps/2 without prediction (the same render rate); "
            "framegen_on at fps with every other frame predicted. dropped = ticks that never "
            "reached ring U (missing frame ids; ring R/U overwrites are among them)"
        )
        print(
            f"presented / rendered with frame generation: {on['presented_over_rendered']:.2f}; "
            f"dropped: {on['dropped']} with, {off['dropped']} without"
        )
    report.write(args.json)
    print(f"report written to {args.json}")
    return 0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _game_counter(port: int, name: str) -> float:
    """A counter from the game process's /metrics (what the game itself counted)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        text = reply.read().decode()
    for line in text.splitlines():
        if line.startswith(f"{name}_total ") or line.startswith(f"{name} "):
            return float(line.split()[-1])
    raise RuntimeError(f"the game exports no {name}")


PREDICTOR_READY_TIMEOUT_S = 180.0


def _wait_for_predictions(stack: LocalStack, ring_u: FrameRing) -> None:
    """Until the first predicted frame: the worker compiles MPE's kernels on a thread
    at start (~18 s with an empty numba cache), and those seconds are not the steady
    state this benchmark measures."""
    print("  waiting for the worker's frame predictor ...", file=sys.stderr)
    deadline = time.monotonic() + PREDICTOR_READY_TIMEOUT_S
    while time.monotonic() < deadline:
        lease = ring_u.acquire_read(0.5)
        if lease is None:
            stack.check_children()
            continue
        with lease:
            if int(lease.header["flags"]) & int(FrameFlags.PREDICTED):
                return
    raise TimeoutError(f"no predicted frame within {PREDICTOR_READY_TIMEOUT_S:.0f} s")


def _measure(config: SessionConfig, args: argparse.Namespace) -> dict[str, Any]:
    total = args.warmup + args.duration
    game_port = _free_port()
    # The game's own count of full renders is the rendered rate: a rendered frame lost
    # on the way to ring U was still rendered (and costs the game as much).
    stack = LocalStack(config, metrics_ports=(game_port, 0))
    stamps: list[np.ndarray] = []
    frame_ids: list[int] = []
    predicted: list[bool] = []
    received_ns: list[int] = []
    with stack:
        stack.wait_ready()
        ring_u = stack.ring_u
        assert ring_u is not None
        ring_u.attach_as_consumer()
        if config.frame_generation:
            _wait_for_predictions(stack, ring_u)
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
                rendered_0 = _game_counter(game_port, "upcast_game_frames_rendered")
                rendered_t0 = time.monotonic()
            if lease is None:
                stack.check_children()
                continue
            with lease:
                record = np.array(lease.header["stamps"], dtype=np.int64)
                record[Stage.ENCODE_START] = (time.monotonic_ns(), time.time_ns())
                frame_id = int(lease.header["frame_id"])
                was_predicted = bool(int(lease.header["flags"]) & FrameFlags.PREDICTED)
            if now >= measure_from:
                stamps.append(record)
                frame_ids.append(frame_id)
                predicted.append(was_predicted)
                received_ns.append(int(record[Stage.ENCODE_START, 0]))
            if now >= next_progress:
                print(
                    f"  {now - measure_from:5.1f}/{args.duration:.0f} s  frames {len(frame_ids)}",
                    file=sys.stderr,
                )
                next_progress += 5.0
        assert stack.ring_r is not None and base_r is not None and base_u is not None
        end_r, end_u = stack.ring_r.counters(), ring_u.counters()
        game_rendered = _game_counter(game_port, "upcast_game_frames_rendered") - rendered_0
        game_rendered_fps = game_rendered / (time.monotonic() - rendered_t0)
        restarts = stack.worker_restarts
    result = _summarize(stamps, frame_ids, received_ns)
    dropped_r = end_r.dropped - base_r.dropped
    dropped_u = end_u.dropped - base_u.dropped
    n_pred = sum(predicted)
    kinds = np.asarray(predicted, dtype=bool)
    mono = np.stack(stamps)[:, :, 0] if stamps else np.zeros((0, STAGE_COUNT), np.int64)
    by_kind = {
        kind: _span_ms(mono[kinds == want], Stage.UPSCALE_START, Stage.UPSCALE_END)
        for kind, want in (("rendered", False), ("predicted", True))
    }
    return {
        "achieved_fps": result["fps"],
        "rendered_fps": game_rendered_fps,
        "frames_received": len(frame_ids),
        "frames_predicted": n_pred,
        "presented_over_rendered": (
            result["fps"] / game_rendered_fps if game_rendered_fps else float("nan")
        ),
        "frames_missing_by_id": result["missing_ids"],
        "ring_r_dropped": dropped_r,
        "ring_u_dropped": dropped_u,
        # Every frame lost on the way (a ring overwrite, a skipped prediction) is a missing id.
        "dropped": result["missing_ids"],
        "worker_restarts": restarts,
        "median_ms": result["stages"]["render_start_to_ring_u_consumer"].get("median_ms"),
        "p95_ms": result["stages"]["render_start_to_ring_u_consumer"].get("p95_ms"),
        "upscale_stage_by_kind": by_kind,
        "stages": result["stages"],
    }


def _print_case(name: str, case: dict[str, Any], fps: float) -> None:
    print(
        f"{name}: fps {case['achieved_fps']:.2f} (target {fps:g}), rendered "
        f"{case['rendered_fps']:.2f}, frames {case['frames_received']} "
        f"({case['frames_predicted']} predicted), missing ids {case['frames_missing_by_id']}, "
        f"dropped ring R {case['ring_r_dropped']} ring U {case['ring_u_dropped']}"
    )
    print(f"{'stage':34} {'p50 ms':>8} {'p95 ms':>8}")
    for stage, s in case["stages"].items():
        if s.get("count"):
            print(f"{stage:34} {s['median_ms']:8.3f} {s['p95_ms']:8.3f}")
    for kind, s in case["upscale_stage_by_kind"].items():
        if s.get("count"):
            print(f"{'upscale (' + kind + ')':34} {s['median_ms']:8.3f} {s['p95_ms']:8.3f}")


def _span_ms(mono: np.ndarray, start: Stage, end: Stage) -> dict[str, float]:
    """Summary of span start -> end over the (N, STAGE_COUNT) monotonic stamps of the
    frames that have both."""
    ok = (mono[:, start] > 0) & (mono[:, end] > 0)
    return summarize_ms((mono[ok, end] - mono[ok, start]) / 1e6) if ok.any() else {}


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
        span = _span_ms(mono, a, b)
        if span:
            stages[name] = span
    stages["render_start_to_ring_u_consumer"] = summarize_ms(
        (mono[:, Stage.ENCODE_START] - mono[:, Stage.RENDER_START]) / 1e6
    )
    duration_s = (received_ns[-1] - received_ns[0]) / 1e9
    fps = (len(received_ns) - 1) / duration_s if duration_s > 0 else 0.0
    ids = np.asarray(frame_ids)
    missing = int((ids[-1] - ids[0] + 1) - len(np.unique(ids)))
    return {"fps": fps, "missing_ids": missing, "stages": stages}
