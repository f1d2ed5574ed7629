"""``upcast bench render``: reference renderer speed per scene (median, p95 ms, fps)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="where to write the report")
    parser.add_argument("--size", default="640x360", help="render size WxH")
    parser.add_argument("--frames", type=int, default=60, help="timed frames per scene")
    parser.add_argument("--warmup", type=int, default=3, help="untimed frames first")
    parser.add_argument("--scenes", default="all", help="comma-separated scene names, or all")
    parser.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    parser.add_argument("--device", default="cpu")


def run(args: argparse.Namespace) -> int:
    import time

    import torch

    from server.frames.frame import Size
    from server.game.render.renderer import Renderer, RenderTargets
    from server.game.render.scenes import parse_scene_list
    from server.ops.report import BenchReport, summarize_ms

    size = Size.parse(args.size)
    scenes = parse_scene_list(args.scenes)
    threads = [int(x) for x in args.threads.split(",")]
    report = BenchReport(
        "render",
        {
            "size": str(size),
            "frames": args.frames,
            "scenes": scenes,
            "threads": threads,
            "device": args.device,
        },
    )
    report.notes.append("time of Renderer.render into preallocated targets at 60 fps scene time")
    print(f"{'scene':16s} {'threads':>7s} {'median ms':>10s} {'p95 ms':>8s} {'fps':>7s}")
    for n_threads in threads:
        torch.set_num_threads(n_threads)
        for name in scenes:
            renderer = Renderer(name, size, device=args.device)
            targets = RenderTargets.allocate(size)
            samples = []
            for i in range(args.warmup + args.frames):
                start = time.perf_counter()
                renderer.render(i, i / 60.0, targets)
                if args.device != "cpu":
                    torch.cuda.synchronize()
                if i >= args.warmup:
                    samples.append((time.perf_counter() - start) * 1e3)
            stats = summarize_ms(samples)
            fps = 1e3 / stats["median_ms"]
            report.add_case(f"{name}@{n_threads}t", scene=name, threads=n_threads, fps=fps, **stats)
            med, p95 = stats["median_ms"], stats["p95_ms"]
            print(f"{name:16s} {n_threads:7d} {med:10.2f} {p95:8.2f} {fps:7.1f}")
    report.write(args.json)
    print(f"wrote {args.json}")
    return 0
