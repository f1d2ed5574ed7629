"""``upcast bench compile_start``: what ``compile=True`` costs a worker at start, cold and warm.

Each case is a fresh process (as a worker start is) that builds the upscaler
through UpscalerHost with ``compile=True`` and upscales a few frames of a scene.
The first start uses an empty inductor cache directory (``TORCHINDUCTOR_CACHE_DIR``),
the second the same directory again: the difference is what the disk cache saves
on every later start of the same code at the same sizes.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from server.ops.report import BenchReport

_CHILD = "from server.bench.compile_start import child; child({!r}, {!r}, {!r}, {})"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="JSON report path")
    parser.add_argument("--methods", default="easu_rcas,temporal", help="comma-separated")
    parser.add_argument("--render-size", default="640x360")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--cache-dir", type=Path, default=None, help="inductor cache (default: a fresh temp dir)"
    )


def child(method: str, render_text: str, display_text: str, threads: int) -> None:
    """One worker-like start: prints a JSON line with the compile and frame times."""
    started = time.monotonic()
    import torch

    from server.frames.frame import Size
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers.host import UpscalerHost

    torch.set_num_threads(threads)
    render, display = Size.parse(render_text), Size.parse(display_text)
    renderer = Renderer("slow_pan", render, scale=display.width / render.width)
    frames = [renderer.render(i, i / 60, RenderTargets.allocate(render)) for i in range(6)]
    host = UpscalerHost(method, display, compile=True)
    ready = time.monotonic()
    calls_ms = []
    for frame in frames:
        t0 = time.perf_counter()
        host.upscale(frame)
        calls_ms.append((time.perf_counter() - t0) * 1e3)
    compiled = getattr(host.upscaler, "compiled", None)
    warmup = max(compiled.warmup_s.values()) if compiled is not None else None
    print(
        json.dumps(
            {
                "import_and_setup_s": ready - started,
                "compile_s": warmup,
                "calls_ms": calls_ms,
                "start_to_last_frame_s": time.monotonic() - started,
            }
        )
    )


def run(args: argparse.Namespace) -> int:
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    cache = args.cache_dir or Path(tempfile.mkdtemp(prefix="upcast-inductor-"))
    report = BenchReport(
        "compile_start",
        {
            "methods": methods,
            "render_size": args.render_size,
            "display_size": args.display_size,
            "threads": args.threads,
            "inductor_cache_dir": str(cache),
            "cases": "cold: first start with this cache dir; warm: the same dir again",
        },
    )
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache)}
    for method in methods:
        for start in ("cold", "warm"):
            code = _CHILD.format(method, args.render_size, args.display_size, args.threads)
            out = subprocess.run(
                [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
            )
            result = json.loads(out.stdout.strip().splitlines()[-1])
            report.add_case(f"{method}/{start}", method=method, start=start, **result)
            print(f"{method} {start}: compile {result['compile_s']:.1f} s", file=sys.stderr)
    report.write(args.json)
    print(f"report written to {args.json}")
    return 0
