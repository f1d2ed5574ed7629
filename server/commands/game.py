"""``upcast game``: the reference game rendering into an existing ring R."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from pathlib import Path

from server.stack.args import add_x11_source_arguments

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ring", required=True, help="ring R name to produce into")
    parser.add_argument("--scene", default="default", help="scene preset")
    parser.add_argument("--size", default="640x360", help="render size WIDTHxHEIGHT")
    parser.add_argument("--scale", type=float, default=2.0, help="display / render (jitter phases)")
    parser.add_argument("--fps", type=float, default=60.0, help="frames per second")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: forever)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--input", type=Path, default=None, help="Unix socket for player input")
    parser.add_argument(
        "--jitter",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="sub-pixel camera jitter (Halton 2,3) for temporal upscalers (default: on)",
    )
    parser.add_argument(
        "--frame-generation",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="render every other frame fully and only the moving objects on the others, "
        "for the worker to predict the rest; --fps stays the rate into ring R (default: off)",
    )
    parser.add_argument(
        "--metrics-port", type=_port, default=0, help="Prometheus /metrics TCP port (0: off)"
    )
    x11 = parser.add_argument_group("X11 source (--source x11: stream a real application)")
    add_x11_source_arguments(x11, size_flag="--size")
    x11.add_argument(
        "--pulse-dir",
        type=Path,
        default=None,
        help="x11: run a PulseAudio server for the application's sound in this folder "
        "(the session records its sink; upcast up passes it)",
    )


def _port(text: str) -> int:
    port = int(text)
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"must be in 0..65535, got {port}")
    return port


def run(args: argparse.Namespace) -> int:
    if args.source == "x11":
        from server.commands.game_x11 import run_x11

        return run_x11(args)
    if args.app is not None or args.x11_display is not None:
        log.error("--app and --x11-display need --source x11")
        return 2
    import torch

    from server.frames.frame import Size
    from server.frames.ring_frames import attach_render_ring
    from server.game.input import InputReceiver
    from server.game.loop import GameLoop
    from server.game.metrics import game_registry
    from server.game.render.renderer import Renderer
    from server.ops.metrics import serve_metrics

    torch.set_num_threads(args.threads)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    renderer = Renderer(
        args.scene, Size.parse(args.size), seed=args.seed, scale=args.scale, jitter=args.jitter
    )
    ring = attach_render_ring(args.ring, wait_s=10)
    display = Size.parse(args.size).scaled(args.scale)
    loop = GameLoop(
        renderer, ring, args.fps, display_size=display, frame_generation=args.frame_generation
    )
    serve_metrics(game_registry(loop), args.metrics_port, "game")
    receiver = (
        InputReceiver(
            args.input,
            loop.push_input,
            on_scale=loop.request_scale,
            on_jitter=loop.request_jitter,
            on_frame_generation=loop.request_frame_generation,
            on_frame_rate=loop.request_frame_rate,
        )
        if args.input
        else None
    )
    log.info(
        "game: scene %s at %s, %.0f fps into %s, frame generation %s",
        args.scene,
        args.size,
        args.fps,
        args.ring,
        "on" if args.frame_generation else "off",
    )
    try:
        stats = loop.run(stop, duration_s=args.duration)
    finally:
        if receiver is not None:
            receiver.close()
        ring.close()
    log.info("game stopped: %s", stats)
    return 0
