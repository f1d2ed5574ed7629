"""``upcast bench app``: real programs streamed as source x11 to headless Chromium.

Per program (server/bench/app/presets.py): the stack as ``upcast up --source x11``
runs it (relay process, game process with Xvfb and the program, worker, the session
on its own event loop), a headless Chromium page that clicks the picture (focus),
taps the program's start keys, then taps its play keys every half second while the
benchmark runs. Reported per program:

- fps the session published and fps the page presented;
- capture ms: the game stage render_start -> render_end, which for source x11 is
  the grab of the display into ring R (timing track, read by the page);
- input-to-photon p50 / p95 from the page: key press -> the first presented frame
  whose capture followed the press's injection (the program's own reaction time,
  one or more of its frames, comes on top and is not in this figure);
- received PSNR: canvas snapshots against the frame the session encoded with the
  same id (thumbnails, 4x box);
- a screenshot of the player page.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from server.bench.app.presets import PRESETS, PresetError
from server.bench.latency import LiveStack, StageCollector, percentiles
from server.bench.page_stats import read_latency, read_stats
from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS, WEB_ROOT
from server.ops.report import BenchReport
from server.serve.snapshots import FrameThumbs, snapshot_psnr
from server.stack.local import SessionConfig

TAP_EVERY_S = 0.5
TAP_HOLD_MS = 100  # a person's tap


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument(
        "--apps", default=",".join(PRESETS), help=f"programs, comma-separated: {', '.join(PRESETS)}"
    )
    parser.add_argument("--seconds", type=float, default=20.0, help="seconds measured per program")
    parser.add_argument("--warmup", type=float, default=6.0, help="seconds before measuring")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--render-size", default="640x360", help="the program's screen")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--upscaler", default="easu_rcas")
    parser.add_argument(
        "--bitrate-kbps", type=int, default=None, help="video bitrate (default: as upcast up)"
    )
    parser.add_argument(
        "--screenshots", type=Path, default=None, help="folder for a PNG of the player per program"
    )


def _tap(page: Any, key: str) -> None:
    page.keyboard.down(key)
    page.wait_for_timeout(TAP_HOLD_MS)
    page.keyboard.up(key)


def _measure(args: argparse.Namespace, name: str, browser: Any, home: Path) -> dict[str, Any]:
    preset = PRESETS[name]
    config = SessionConfig(
        source="x11",
        app=preset.command(args.render_size, home),
        render_size=args.render_size,
        display_size=args.display_size,
        fps=args.fps,
        upscaler=args.upscaler,
    )
    thumbs = FrameThumbs()
    bitrate = None if args.bitrate_kbps is None else args.bitrate_kbps * 1000
    with LiveStack(config, frame_tap=thumbs, bitrate=bitrate) as live:
        page = browser.new_page(viewport={"width": 1000, "height": 720})
        try:
            page.goto(live.player_url(overlay="1"))
            page.wait_for_function(
                "() => window.upcast && window.upcast.stats().framesPresented > 0", timeout=60_000
            )
            page.click("#screen", position={"x": 5, "y": 5})  # focus, away from menus
            collector = StageCollector.empty()
            warm_end = time.monotonic() + args.warmup
            for key in preset.start_keys:
                _tap(page, key)
            while time.monotonic() < warm_end:
                page.wait_for_timeout(500)
                collector.update(read_latency(page), keep=False)
            session = live.session
            assert session is not None
            start = read_stats(page)
            published0 = session.broadcast.stats.frames_published
            t0 = time.monotonic()
            taps = 0
            while time.monotonic() - t0 < args.seconds:
                _tap(page, preset.play_keys[taps % len(preset.play_keys)])
                taps += 1
                page.wait_for_timeout(int(TAP_EVERY_S * 1000) - TAP_HOLD_MS)
                collector.update(read_latency(page))
                live.check()
            elapsed = time.monotonic() - t0
            end = read_stats(page)
            published = session.broadcast.stats.frames_published - published0
            psnr = snapshot_psnr(page, thumbs, count=10)
            if args.screenshots is not None:
                args.screenshots.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(args.screenshots / f"x11_{name}.png"))
        finally:
            page.close()
    photon = [float(x) for x in end["inputToPhoton"]["samples"]]
    capture = percentiles(collector.samples["render"])
    print(
        f"  {name}: {published / elapsed:.1f} fps published, "
        f"{(end['framesPresented'] - start['framesPresented']) / elapsed:.1f} presented, "
        f"capture p50 {capture['p50_ms']} ms, input-to-photon p50 "
        f"{np.percentile(photon, 50) if photon else None} ms, PSNR median "
        f"{statistics.median(psnr):.1f} dB",
        file=sys.stderr,
    )
    return {
        "name": name,
        "program": preset.program,
        "kind": preset.kind,
        "seconds": round(elapsed, 2),
        "server_fps": round(published / elapsed, 2),
        "page_fps": round((end["framesPresented"] - start["framesPresented"]) / elapsed, 2),
        "capture": capture,
        "total_latency": percentiles(collector.samples["total"]),
        "input_to_photon": percentiles(photon),
        "taps": taps,
        "received_psnr_db": {
            "median": round(statistics.median(psnr), 2),
            "min": round(min(psnr), 2),
            "count": len(psnr),
        },
        "median_ms": capture["median_ms"],
        "p95_ms": capture["p95_ms"],
    }


def run(args: argparse.Namespace) -> int:
    if not CHROMIUM.exists():
        print("upcast bench app: needs /usr/bin/chromium", file=sys.stderr)
        return 2
    if not (WEB_ROOT / "index.html").is_file():
        print("upcast bench app: build client_web first (./dev build)", file=sys.stderr)
        return 2
    names = [n.strip() for n in args.apps.split(",") if n.strip()]
    unknown = [n for n in names if n not in PRESETS]
    if unknown or not names:
        print(
            f"upcast bench app: unknown --apps {', '.join(unknown) or '(none)'}; "
            f"known: {', '.join(PRESETS)}",
            file=sys.stderr,
        )
        return 2
    from playwright.sync_api import sync_playwright

    report = BenchReport(
        "app",
        {
            "apps": names,
            "render_size": args.render_size,
            "display_size": args.display_size,
            "fps": args.fps,
            "upscaler": args.upscaler,
            "bitrate_kbps": args.bitrate_kbps,
            "seconds": args.seconds,
            "tap_every_s": TAP_EVERY_S,
            "transport": "loopback, relay process, headless Chromium (WebTransport)",
        },
    )
    with sync_playwright() as pw, tempfile.TemporaryDirectory(prefix="upcast-bench-app-") as tmp:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            for name in names:
                print(f"upcast bench app: {name} for {args.seconds:.0f} s", file=sys.stderr)
                try:
                    report.add_case(**_measure(args, name, browser, Path(tmp) / name))
                except PresetError as exc:
                    print(f"upcast bench app: {exc}", file=sys.stderr)
                    return 2
        finally:
            browser.close()
    report.notes.append(
        "median_ms / p95_ms: capture (render_start -> render_end of source x11: the grab "
        "into ring R); input_to_photon excludes the program's own reaction time; "
        "received_psnr_db: canvas against the session's encoded frame with the same id"
    )
    report.write(args.json)
    print(f"wrote {args.json}")
    return 0
