"""``upcast preview``: game + upscaler worker + a local MJPEG preview page, no streaming server.

For looking at the upscalers without a WebTransport browser; ``upcast up`` runs the
real stack (session, relay, web player)."""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import signal
import socket
import sys
import threading
import time
from typing import Any

from server.stack.args import add_session_arguments, session_config_from

log = logging.getLogger(__name__)

CHECK_INTERVAL_S = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_session_arguments(parser)
    parser.add_argument(
        "--host", default="127.0.0.1", help="address the preview binds (e.g. 0.0.0.0 or ::)"
    )
    parser.add_argument("--port", type=int, default=8080, help="preview HTTP port")
    parser.add_argument(
        "--preview-fps",
        type=float,
        default=30.0,
        help="most JPEG frames per second the preview encodes",
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )


def _port_problem(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be bound, or None; checked before spawning anything."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as exc:
        return _bind_message(host, port, exc)
    return None


def _bind_message(host: str, port: int, exc: OSError) -> str:
    if exc.errno == errno.EADDRINUSE:
        return (
            f"upcast preview: port {port} on {host} is already in use; "
            f"pick another with --port (e.g. --port {port + 1})"
        )
    if exc.errno == errno.EACCES:
        return f"upcast preview: not allowed to bind port {port}; use --port above 1023"
    reason = exc.strerror or exc
    return f"upcast preview: cannot listen on {host}:{port} ({reason}); check --host/--port"


def run(args: argparse.Namespace) -> int:
    from server.stack.local import LocalStack
    from server.stack.preview import PreviewServer

    config = session_config_from(args)
    if config is None:
        return 2
    if not 0 <= args.port <= 65535:
        print(f"upcast preview: --port must be 0..65535, got {args.port}", file=sys.stderr)
        return 2
    if args.preview_fps <= 0:
        print(
            f"upcast preview: --preview-fps must be positive, got {args.preview_fps}",
            file=sys.stderr,
        )
        return 2
    if args.duration is not None and args.duration <= 0:
        print(f"upcast preview: --duration must be positive, got {args.duration}", file=sys.stderr)
        return 2
    problem = _port_problem(args.host, args.port)
    if problem is not None:
        print(problem, file=sys.stderr)
        return 1

    stop = threading.Event()
    started = threading.Event()

    def _on_signal(signum: int, _frame: Any) -> None:
        log.info("%s received: stopping", signal.Signals(signum).name)
        stop.set()
        if not started.is_set():
            raise KeyboardInterrupt  # leave wait_ready() at once; cleanup runs below

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _on_signal)

    stack = LocalStack(config)
    preview: PreviewServer | None = None
    code = 0
    try:
        stack.start()
        stack.wait_ready()
        assert stack.ring_u is not None

        def session_info() -> dict[str, Any]:
            return {
                "name": config.name,
                "scene": config.scene,
                "render_size": config.render_size,
                "display_size": config.display_size,
                "game_pid": stack.game.pid if stack.game is not None else None,
                "worker_pid": stack.worker.pid if stack.worker is not None else None,
                "worker_restarts": stack.worker_restarts,
            }

        preview = PreviewServer(
            stack.ring_u,
            stack.control_path,
            stack.input_path,
            args.host,
            args.port,
            args.preview_fps,
            session_info=session_info,
            on_upscaler_set=stack.remember_upscaler,
        )
        try:
            preview.start()
        except OSError as exc:
            preview = None
            print(_bind_message(args.host, args.port, exc), file=sys.stderr)
            return 1
        started.set()
        where = " (listening on all interfaces)" if args.host in ("0.0.0.0", "::", "") else ""
        print(f"upcast preview is up: watch at {preview.url}{where}  (Ctrl-C to stop)", flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.wait(CHECK_INTERVAL_S):
            stack.check_children()
            if deadline is not None and time.monotonic() >= deadline:
                log.info("duration of %.0f s reached: stopping", args.duration)
                break
    except KeyboardInterrupt:
        print("upcast preview: interrupted while starting", file=sys.stderr)
        code = 130
    except TimeoutError as exc:
        print(f"upcast preview: {exc}", file=sys.stderr)
        code = 1
    except RuntimeError as exc:  # the game died
        print(f"upcast preview: {exc}", file=sys.stderr)
        code = 1
    finally:
        # A second Ctrl-C while cleaning up must not leave rings behind.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
        if preview is not None:
            with contextlib.suppress(Exception):
                preview.stop()
        stack.stop()
        log.info("upcast stopped; session %s cleaned up", config.name)
    return code
