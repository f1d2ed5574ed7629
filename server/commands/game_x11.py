"""``upcast game --source x11``: an X11 application captured into ring R.

The same loop as the built-in game (server/game/loop.py) with an X11Source as its
renderer: no torch is imported, no jitter, no frame generation, no scale changes
(the captured screen has the size the application draws at). The process's exit
code is the application's when it ended the run, so the stack can say why.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import signal
import threading

log = logging.getLogger(__name__)

# Exit code when the source could not start (bad --app, no Xvfb, no display): the
# stack tells it from the application's own codes (sysexits' EX_CONFIG).
SOURCE_FAILED_CODE = 78


def run_x11(args: argparse.Namespace) -> int:
    from server.frames.frame import Size
    from server.frames.ring_frames import attach_render_ring
    from server.game.input import InputReceiver
    from server.game.loop import GameLoop
    from server.game.metrics import game_registry
    from server.game.x11.app import ApplicationError
    from server.game.x11.errors import DisplayError
    from server.game.x11.source import X11Source
    from server.ops.metrics import serve_metrics

    if args.frame_generation:
        log.error("--frame-generation needs depth and motion, which an X11 source does not give")
        return 2
    try:
        command = shlex.split(args.app) if args.app else None
    except ValueError as exc:
        log.error("--app %r does not parse as a command line: %s", args.app, exc)
        return 2
    if command is None and args.x11_display is None:
        log.error("--source x11 needs --app (a program to start) or --x11-display (one to capture)")
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    size = Size.parse(args.size)
    try:
        source = X11Source(
            size,
            command,
            display=args.x11_display,
            on_app_exit=args.app_exit,
            pulse_dir=args.pulse_dir,
        )
    except (DisplayError, ApplicationError, OSError) as exc:
        log.error("X11 source: %s", exc)
        return SOURCE_FAILED_CODE
    try:
        ring = attach_render_ring(args.ring, wait_s=10)
        loop = GameLoop(source, ring, args.fps)
        serve_metrics(game_registry(loop), args.metrics_port, "game")
        receiver = (
            InputReceiver(
                args.input,
                loop.push_input,
                on_frame_rate=loop.request_frame_rate,
                convert=lambda message: message,
            )
            if args.input
            else None
        )
        log.info(
            "game: X11 display %s at %s, %.0f fps into %s%s",
            source.display,
            size,
            args.fps,
            args.ring,
            f", application: {args.app}" if args.app else "",
        )
        try:
            stats = loop.run(stop, duration_s=args.duration)
        finally:
            if receiver is not None:
                receiver.close()
            ring.close()
    finally:
        source.close()
    log.info("game stopped: %s", stats)
    return loop.ended.code if loop.ended is not None else 0
