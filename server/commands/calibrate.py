"""``upcast calibrate``: measure this machine's times for adaptive quality, cache them.

Sessions under ``--quality auto`` start from the table of speed against error that ships
with upcast; its PSNR holds on any machine, its times only on the one that measured them.
This command times every upscaler at every scale here, through the worker's code path,
and writes the result where every later session on this machine finds it (the log line
``quality: figures from ...`` says which table a session uses).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from server.frames.frame import Size
from server.ops.machine import usable_cores
from server.ops.progress import progress

# A 1-minute load average above this share of the cores: other work is running.
BUSY_LOAD_SHARE = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--from-eval",
        type=Path,
        default=None,
        metavar="REPORT",
        help="take the upscalers' times from this `upcast eval upscalers` JSON report "
        "(run on this machine) instead of measuring",
    )
    parser.add_argument(
        "--methods",
        default="",
        help="comma-separated methods to measure (default: all in the table; the others "
        "keep the shipped times)",
    )
    parser.add_argument("--frames", type=int, default=12, help="timed frames per method and scale")
    parser.add_argument("--scene", default="default", help="the scene rendered for the timings")
    parser.add_argument(
        "--display-size",
        default="",
        help="WxH the times are measured at (default: the shipped table's, 1280x720); the "
        "controller scales them by pixels",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="CPU threads while timing: the worker's (upcast up --worker-threads)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="where to write (default: this machine's cache file, which sessions read; "
        "$UPCAST_CACHE_DIR or $XDG_CACHE_HOME/upcast)",
    )
    parser.add_argument(
        "--show", action="store_true", help="print which table sessions here use, and exit"
    )


def _size(text: str) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        size = Size.parse(text)
    except ValueError as exc:
        raise SystemExit(f"upcast calibrate: --display-size: {exc}") from None
    if size.width < 16 or size.height < 16:
        raise SystemExit("upcast calibrate: --display-size must be at least 16x16")
    return size.width, size.height


def run(args: argparse.Namespace) -> int:
    from server.ops.cpu_threads import set_cpu_threads
    from server.session.quality.calibrate import (
        calibration_path,
        load_machine_figures,
        measure_times,
        stamp,
        times_from_eval,
    )
    from server.session.quality.figures import FIGURES_PATH, FiguresError

    if args.show:
        print(f"sessions on this machine use {load_machine_figures().source}")
        return 0
    if args.frames < 1:
        print("upcast calibrate: --frames must be at least 1", file=sys.stderr)
        return 2
    base = json.loads(FIGURES_PATH.read_text())
    started = time.monotonic()
    try:
        if args.from_eval is not None:
            try:
                report = json.loads(args.from_eval.read_text())
            except (OSError, ValueError) as exc:
                print(f"upcast calibrate: cannot read {args.from_eval}: {exc}", file=sys.stderr)
                return 2
            table = stamp(times_from_eval(base, report), f"eval report {args.from_eval}")
        else:
            set_cpu_threads(max(1, args.threads))
            _warn_if_busy()
            methods = [m.strip() for m in args.methods.split(",") if m.strip()]
            progress(
                f"calibrate: timing {len(methods) or len(base['methods'])} methods x 3 scales, "
                f"{args.frames} frames each, {args.threads} thread(s); about a minute"
            )
            table = measure_times(
                base,
                methods=methods or None,
                display=_size(args.display_size),
                frames=args.frames,
                scene=args.scene,
                on_progress=progress,
            )
            table = stamp(table, f"measured, {args.frames} frames, {args.threads} thread(s)")
    except (FiguresError, ValueError) as exc:
        print(f"upcast calibrate: {exc}", file=sys.stderr)
        return 2
    out: Path = args.out or calibration_path(table["calibration"]["key"])
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(table, indent=1) + "\n")
    tmp.replace(out)  # a session starting now reads the old file or the new, never half
    _print_against_shipped(table, base)
    kept = table["calibration"]["kept_shipped_times"]
    if kept:
        print(f"kept the shipped times for {', '.join(kept)}")
    print(f"wrote {out} in {time.monotonic() - started:.0f} s ({table['machine']})")
    return 0


def _warn_if_busy() -> None:
    """Times measured beside other work are that work's as much as ours: say so."""
    cores = usable_cores()
    load = os.getloadavg()[0]
    if load > BUSY_LOAD_SHARE * cores:
        progress(
            f"calibrate: warning: this machine is busy (load average {load:.1f} on {cores} "
            "cores); the times measured now will be slow. Run again when it is idle."
        )


def _print_against_shipped(table: dict[str, object], base: dict[str, object]) -> None:
    """This machine's median times against the shipped table's, per pixel of display."""
    ours, theirs = table["methods"], base["methods"]
    assert isinstance(ours, dict) and isinstance(theirs, dict)
    px = float(table["display_pixels"]) / float(base["display_pixels"])  # type: ignore[arg-type]
    print(f"{'method':<14} {'scale':>5} {'here ms':>8} {'shipped':>8} {'ratio':>6}")
    for name, entry in ours.items():
        for scale, ms, ref in zip(
            entry["scales"], entry["median_ms"], theirs[name]["median_ms"], strict=True
        ):
            ratio = ms / (ref * px) if ref > 0 else float("nan")
            print(f"{name:<14} {scale:>5g} {ms:>8.2f} {ref * px:>8.2f} {ratio:>6.2f}")
