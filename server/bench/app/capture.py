"""``upcast bench capture``: reading a real X screen's pixels, per grabber, against memcpy.

Issue 22 streams an unmodified application from a private Xvfb; every frame
starts with a capture of its screen into ring R's colour plane, so the capture
must cost little next to the frame budget (target: 2 ms at 640x360 on 2 cores).
For each size, one Xvfb shows a known picture (server/game/x11/pattern.py) and
every grabber of server/game/x11/grabbers.py writes it through ``ScreenCapture``
into one RGB buffer, the pixels checked exactly; a numpy copy of the same
number of bytes is the floor. Calls are interleaved (the order rotates every
frame) over several rounds, so a neighbour's load hits every method alike.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from server.frames.frame import Size
from server.game.x11.capture import ScreenCapture
from server.game.x11.display import VirtualDisplay
from server.game.x11.grabbers import DEFAULT_GRABBER, GRABBERS
from server.game.x11.pattern import card_rects, paint, render
from server.ops.report import BenchReport, summarize_ms

TARGET_MS = 2.0
TARGET_SIZE = Size(640, 360)
MEMCPY = "memcpy"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="JSON report path")
    parser.add_argument("--sizes", default="640x360,1280x720", help="screen sizes, comma-separated")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (one ratio each)")
    parser.add_argument("--frames", type=int, default=60, help="timed grabs per method and round")
    parser.add_argument("--grabbers", default=",".join(GRABBERS), help=f"of {', '.join(GRABBERS)}")


def _time_rounds(
    methods: dict[str, Callable[[], None]], frames: int, rounds: int
) -> list[dict[str, list[float]]]:
    names = list(methods)
    out = []
    for _ in range(rounds):
        times: dict[str, list[float]] = {n: [] for n in names}
        for i in range(frames + 1):  # frame 0 of each round warms caches, untimed
            for n in names[i % len(names) :] + names[: i % len(names)]:
                t0 = time.perf_counter_ns()
                methods[n]()
                if i:
                    times[n].append((time.perf_counter_ns() - t0) / 1e6)
        out.append(times)
    return out


def _grab_call(capture: ScreenCapture, out: np.ndarray[Any, Any]) -> Callable[[], None]:
    return lambda: capture.grab_into(out)


def _open(
    name: str, display: VirtualDisplay, size: Size, expected: np.ndarray[Any, Any]
) -> tuple[ScreenCapture | None, dict[str, Any]]:
    """The grabber's capture and its pixel check, or None and why it is unusable."""
    try:
        capture = ScreenCapture(display.name, size.width, size.height, grabber=name)
        out = np.zeros_like(expected)
        capture.grab_into(out)
    except Exception as exc:  # a grabber that cannot run here is reported, not fatal
        return None, {"available": False, "error": repr(exc)}
    wrong = int((out != expected).any(axis=2).sum())
    return capture, {"available": True, "pixels_exact": wrong == 0, "wrong_pixels": wrong}


def _measure_size(
    report: BenchReport, size: Size, grabbers: list[str], frames: int, rounds: int
) -> None:
    rects = card_rects(size.width, size.height)
    expected = render(rects, size.width, size.height)
    with VirtualDisplay.start(size.width, size.height) as display:
        paint(display.name, rects)
        out = np.zeros_like(expected)
        src, dst = np.ones(expected.nbytes, np.uint8), np.zeros(expected.nbytes, np.uint8)
        methods: dict[str, Callable[[], None]] = {MEMCPY: lambda: np.copyto(dst, src)}
        checks: dict[str, dict[str, Any]] = {}
        captures: list[ScreenCapture] = []
        for name in grabbers:
            capture, checks[name] = _open(name, display, size, expected)
            if capture is not None:
                captures.append(capture)
                methods[name] = _grab_call(capture, out)
        try:
            timed = _time_rounds(methods, frames, rounds)
            for name in grabbers:  # the picture is still right after all the grabs
                if name in methods:
                    out[...] = 0
                    methods[name]()
                    checks[name]["pixels_exact_after"] = bool((out == expected).all())
        finally:
            for capture in captures:
                capture.close()
    _report_size(report, size, grabbers, checks, timed)


def _report_size(
    report: BenchReport,
    size: Size,
    grabbers: list[str],
    checks: dict[str, dict[str, Any]],
    timed: list[dict[str, list[float]]],
) -> None:
    memcpy = summarize_ms(x for r in timed for x in r[MEMCPY])
    report.add_case(
        f"{size}/{MEMCPY}", size=str(size), bytes=size.width * size.height * 3, **memcpy
    )
    for name in grabbers:
        if not checks[name]["available"]:
            report.add_case(f"{size}/{name}", size=str(size), grabber=name, **checks[name])
            report.notes.append(f"{size} {name}: unavailable ({checks[name]['error']})")
            continue
        t = summarize_ms(x for r in timed for x in r[name])
        ratios = [float(np.median(r[name]) / np.median(r[MEMCPY])) for r in timed]
        ratio = float(np.median(ratios))
        report.add_case(
            f"{size}/{name}",
            size=str(size),
            grabber=name,
            default=name == DEFAULT_GRABBER,
            **checks[name],
            **t,
            ratio_to_memcpy_per_round=ratios,
        )
        report.add_ratio(f"{size} {name} / memcpy time", name, MEMCPY, ratio)
        exact = checks[name]["pixels_exact"] and checks[name]["pixels_exact_after"]
        verdict = ""
        if size == TARGET_SIZE:
            passed = exact and t["median_ms"] <= TARGET_MS
            verdict = f"{'PASS' if passed else 'FAIL'} (target {TARGET_MS:g} ms, exact pixels): "
        report.notes.append(
            f"{verdict}{size} {name}: median {t['median_ms']:.3f} ms, p95 {t['p95_ms']:.3f} ms, "
            f"{ratio:.1f}x memcpy ({memcpy['median_ms']:.3f} ms), "
            f"pixels {'exact' if exact else 'WRONG'}"
        )


def _fastest_note(report: BenchReport, size: Size) -> None:
    timed = [
        c
        for c in report.cases
        if c.get("size") == str(size) and c.get("grabber") and c.get("pixels_exact")
    ]
    if not timed:
        return
    fastest = min(timed, key=lambda c: float(c["median_ms"]))
    ok = fastest["grabber"] == DEFAULT_GRABBER
    report.notes.append(
        f"{'PASS' if ok else 'FAIL'}: at {size} the fastest exact grabber is "
        f"{fastest['grabber']} and the default is {DEFAULT_GRABBER}"
    )


def run(args: argparse.Namespace) -> int:
    sizes = [Size.parse(s.strip()) for s in args.sizes.split(",") if s.strip()]
    grabbers = [g.strip() for g in args.grabbers.split(",") if g.strip()]
    unknown = sorted(set(grabbers) - set(GRABBERS))
    if unknown:
        raise SystemExit(f"--grabbers: unknown {', '.join(unknown)}; one of {', '.join(GRABBERS)}")
    report = BenchReport(
        "bench_capture",
        {
            "sizes": [str(s) for s in sizes],
            "grabbers": grabbers,
            "default_grabber": DEFAULT_GRABBER,
            "frames": args.frames,
            "rounds": args.rounds,
            "target_ms": TARGET_MS,
            "target_size": str(TARGET_SIZE),
            "screen": "Xvfb 24-bit, colour bars with a one-pixel frame (pattern.py)",
            "reference": "numpy copy of the same number of bytes as the RGB frame",
        },
    )
    for size in sizes:
        _measure_size(report, size, grabbers, args.frames, args.rounds)
        _fastest_note(report, size)
        print(f"{size} done")
    report.write(args.json)
    print("\n".join(report.notes))
    print(f"report written to {args.json}")
    return 0
