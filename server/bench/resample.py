"""``upcast bench resample``: our plain resamplers against OpenCV's resize, same frames.

Issue 19 asks that where a library resampler gives the same images faster, the
CPU path use it. Per scale, on a game frame (unjittered, as spatial methods get
it) and on uniform noise (neighbours up to 255 apart: the worst case for
rounding), each pair is compared pixel by pixel, borders included (max level
difference, the same with a 4-pixel border left out, share of pixels more than
one level apart), and timed: ``upscale`` calls (what the worker pays before the
ring U copy), interleaved in one process, rotated each call, over several
rounds, each round's ratio reported.

Pairs (``+torch``: the method's torch path, what it ran before issue 19): bilinear
against OpenCV's linear, nearest-exact against OpenCV's exact nearest (the CPU
paths now take them where they match, see ``upscalers/spatial/resample.py``), bicubic
(Catmull-Rom) against OpenCV's cubic (a = -0.75), lanczos2 against OpenCV's
Lanczos-4.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import torch

from server.frames.frame import RenderFrame, Size
from server.game.render.renderer import Renderer, RenderTargets
from server.ops.cpu_threads import set_cpu_threads
from server.ops.report import BenchReport, summarize_ms
from upscalers import registry
from upscalers.output import to_uint8
from upscalers.spatial.cv_resample import cv_resize

Resample = Callable[[RenderFrame, Size], torch.Tensor]
# (ours, the library's): the first is what the project shipped before issue 19.
PAIRS = (
    ("bilinear+torch", "cv_linear"),
    ("bicubic", "cv_cubic"),
    ("nearest+torch", "cv_nearest_exact"),
    ("lanczos2", "cv_lanczos4"),
)
BORDER = 4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="JSON report path")
    parser.add_argument("--scene", default="slow_pan", help="game scene of the frame")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--scales", default="1.5,2,3", help="display/render, comma-separated")
    parser.add_argument("--calls", type=int, default=30, help="timed calls per method and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (one ratio each)")
    parser.add_argument("--threads", type=int, default=2, help="torch and OpenCV CPU threads")


def _methods() -> dict[str, Resample]:
    def cv(interpolation: int) -> Resample:
        return lambda frame, size: cv_resize(frame.color, size, interpolation)

    ups = {
        "bilinear+torch": registry.create("bilinear", backend="torch"),
        "bicubic": registry.create("bicubic"),
        "nearest+torch": registry.create("nearest", backend="torch"),
        "lanczos2": registry.create("lanczos2"),
    }
    methods: dict[str, Resample] = {k: u.upscale for k, u in ups.items()}
    methods["cv_linear"] = cv(cv2.INTER_LINEAR)
    methods["cv_cubic"] = cv(cv2.INTER_CUBIC)
    methods["cv_nearest_exact"] = cv(cv2.INTER_NEAREST_EXACT)
    methods["cv_lanczos4"] = cv(cv2.INTER_LANCZOS4)
    return methods


def _difference(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8]) -> dict[str, float]:
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    inner = d[BORDER:-BORDER, BORDER:-BORDER]
    return {
        "max_levels": int(d.max()),
        "max_levels_inside": int(inner.max()) if inner.size else 0,
        "share_over_1_level": float((d > 1).any(axis=2).mean()),
    }


def _noise_frame(frame: RenderFrame) -> RenderFrame:
    h, w, _ = frame.color.shape
    color = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    return RenderFrame(color, frame.depth, frame.motion, frame.dynamic_mask, frame.meta)


def _time_rounds(
    methods: dict[str, Resample], frame: RenderFrame, display: Size, calls: int, rounds: int
) -> list[dict[str, list[float]]]:
    names = list(methods)
    out = []
    for _ in range(rounds):
        times: dict[str, list[float]] = {n: [] for n in names}
        for i in range(calls + 1):  # call 0 of each round warms caches, untimed
            for n in names[i % len(names) :] + names[: i % len(names)]:
                t0 = time.perf_counter_ns()
                methods[n](frame, display)
                if i:
                    times[n].append((time.perf_counter_ns() - t0) / 1e6)
        out.append(times)
    return out


def run(args: argparse.Namespace) -> int:
    set_cpu_threads(args.threads)
    display = Size.parse(args.display_size)
    scales = [float(s) for s in args.scales.split(",") if s.strip()]
    report = BenchReport(
        "bench_resample",
        {
            "scene": args.scene,
            "display_size": str(display),
            "scales": scales,
            "calls": args.calls,
            "rounds": args.rounds,
            "threads": args.threads,
            "opencv": cv2.__version__,
            "pairs": [list(p) for p in PAIRS],
            "reference": "each pair's first method (the project's torch resampler)",
        },
    )
    methods = _methods()
    for scale in scales:
        render = Size(round(display.width / scale), round(display.height / scale))
        renderer = Renderer(args.scene, render, scale=scale, jitter=False)
        game = renderer.render(0, 0.5, RenderTargets.allocate(render))
        rounds = _time_rounds(methods, game, display, args.calls, args.rounds)
        for ours, library in PAIRS:
            diffs = {
                label: _difference(
                    to_uint8(methods[ours](frame, display)),
                    to_uint8(methods[library](frame, display)),
                )
                for label, frame in (("game", game), ("noise", _noise_frame(game)))
            }
            ratios = [float(np.median(r[ours]) / np.median(r[library])) for r in rounds]
            ratio = float(np.median(ratios))
            times = {}
            for name in (ours, library):
                t = summarize_ms(x for r in rounds for x in r[name])
                times[f"{name}_median_ms"] = t["median_ms"]
                times[f"{name}_p95_ms"] = t["p95_ms"]
            report.add_case(
                f"{scale:g}x/{ours} vs {library}",
                scale=scale,
                render_size=str(render),
                **diffs,
                **times,
                time_ratio_ours_over_library_per_round=ratios,
            )
            report.add_ratio(f"{scale:g}x {ours} / {library} time", ours, library, ratio)
            same = all(d["max_levels"] <= 1 for d in diffs.values())
            report.notes.append(
                f"{scale:g}x {ours} vs {library}: "
                f"{'the same images' if same else 'different images'} (max "
                f"{diffs['game']['max_levels']:g} levels on the game frame, "
                f"{diffs['noise']['max_levels']:g} on noise), library "
                f"{ratio:.2f}x as fast (rounds: {', '.join(f'{x:.2f}' for x in ratios)})"
            )
        print(f"{scale:g}x done")
    report.write(args.json)
    print("\n".join(report.notes))
    print(f"report written to {args.json}")
    return 0
