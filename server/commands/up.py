"""``upcast up``: the whole stack on one machine, printing where to watch.

Processes: the game (renders into ring R), the upscaler worker (ring R -> ring
U), the relay (moq-lite over WebTransport, serves the web player) and, in this
process, the streaming session (ring U -> CMAF -> broadcast on the relay,
viewer inputs -> game and worker). A dead worker or relay is restarted; the
game never waits for either.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from server.auth.keys import KeyFileError
from server.browser_paths import WEB_ROOT
from server.stack_args import add_session_arguments, session_config_from

if TYPE_CHECKING:
    from server.auth.minting import SessionTokens
    from server.stack import SessionConfig
    from server.stream_config import StreamConfig

log = logging.getLogger(__name__)

CHECK_INTERVAL_S = 0.5
CONNECT_TIMEOUT_S = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_session_arguments(parser)
    parser.add_argument(
        "--host", default="::", help="relay bind address (default :: = all, dual stack)"
    )
    parser.add_argument("--port", type=int, default=4443, help="relay port, UDP (QUIC) and TCP")
    parser.add_argument("--broadcast", default="game", help="broadcast name (default: game)")
    parser.add_argument(
        "--bitrate-kbps",
        type=int,
        default=None,
        help="video bitrate (default: scaled 6 Mbit/s 720p60)",
    )
    parser.add_argument(
        "--gop-seconds", type=float, default=2.0, help="periodic keyframe interval (seconds)"
    )
    parser.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        help="TCP port of the session's Prometheus metrics (default: relay port + 1; 0 = off)",
    )
    parser.add_argument(
        "--web-root", type=Path, default=WEB_ROOT, help="built web client (client_web/dist)"
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )
    parser.add_argument(
        "--auth-key",
        type=Path,
        default=None,
        help="relay key file (JWK) to sign tokens with (default: a new one, gone at exit)",
    )


def _problem(args: argparse.Namespace) -> str | None:
    if args.duration is not None and args.duration <= 0:
        return f"--duration must be positive, got {args.duration}"
    if args.auth_key is not None and not args.auth_key.is_file():
        return (
            f"--auth-key {args.auth_key} does not exist"
            f" (make one: upcast token generate --key {args.auth_key})"
        )
    if not (args.web_root / "index.html").is_file():
        return (
            f"the web client is not built ({args.web_root}/index.html missing): "
            "run ./dev up, or cd client_web && npm ci && npm run build"
        )
    return None


def _browser_host(bind: str) -> str:
    # Chromium resolves localhost to ::1 first; a dual-stack "::" bind takes both.
    if bind in ("::", "", "0.0.0.0"):
        return "localhost" if bind != "0.0.0.0" else "127.0.0.1"
    return f"[{bind}]" if ":" in bind else bind


def _session_host(bind: str) -> str:
    if bind in ("::", "", "0.0.0.0"):
        return "127.0.0.1"
    return f"[{bind}]" if ":" in bind else bind


def _keys(given: Path | None, tmp: Path, broadcast: str) -> tuple[Path, SessionTokens]:
    """The relay's key file (``given``, or a new one in ``tmp``) and the session's and
    player's tokens signed with it."""
    from server.auth import generate_key, load_key
    from server.auth.minting import session_tokens

    path = given
    if path is None:
        path = tmp / "relay.jwk"
        generate_key(path)
    return path, session_tokens(load_key(path), broadcast)


def run(args: argparse.Namespace) -> int:
    from server.config_errors import validated
    from server.event_loop import install_uvloop
    from server.stream_config import StreamConfig

    problem = _problem(args)
    if problem is not None:
        print(f"upcast up: {problem}", file=sys.stderr)
        return 2
    config = session_config_from(args)
    stream = validated(
        StreamConfig,
        "stream",
        host=args.host,
        port=args.port,
        broadcast=args.broadcast,
        bitrate_kbps=args.bitrate_kbps,
        gop_seconds=args.gop_seconds,
        metrics_port=args.metrics_port,
    )
    if config is None or stream is None:
        return 2
    install_uvloop()
    return asyncio.run(_main(args, config, stream))


async def _main(args: argparse.Namespace, config: SessionConfig, stream: StreamConfig) -> int:
    from prometheus_client import CollectorRegistry, start_http_server

    from server.frame import Size
    from server.relay_process import RelayProcess
    from server.session.runner import StreamingSession, StreamSettings
    from server.stack import LocalStack

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    key_dir = tempfile.TemporaryDirectory(prefix="upcast-key-")
    try:
        key_path, tokens = _keys(args.auth_key, Path(key_dir.name), stream.broadcast)
    except KeyFileError as exc:
        key_dir.cleanup()
        print(f"upcast up: --auth-key: {exc}", file=sys.stderr)
        return 2
    relay = RelayProcess(stream.host, stream.port, args.web_root, auth_key=key_path)
    stack = LocalStack(config)
    session_task: asyncio.Task[None] | None = None
    code = 0
    try:
        try:
            endpoint = await loop.run_in_executor(None, relay.start)
        except (RuntimeError, TimeoutError) as exc:
            print(f"upcast up: relay failed to start on port {stream.port}: {exc}", file=sys.stderr)
            return 1
        await loop.run_in_executor(None, stack.start)
        await loop.run_in_executor(None, stack.wait_ready)
        assert stack.ring_u is not None
        registry = CollectorRegistry()
        metrics_port = stream.session_metrics_port
        if metrics_port:
            try:
                start_http_server(metrics_port, registry=registry)
            except OSError as exc:
                log.warning("session metrics port %d unavailable: %s", metrics_port, exc)
                metrics_port = 0
        settings = StreamSettings(
            relay_url=f"http://{_session_host(stream.host)}:{endpoint.port}/",
            broadcast=stream.broadcast,
            fps=config.fps,
            bitrate=None if stream.bitrate_kbps is None else stream.bitrate_kbps * 1000,
            gop_seconds=stream.gop_seconds,
            upscaler=config.upscaler,
            scale=config.scale,
            token=tokens.publisher,
        )
        session = StreamingSession(
            settings,
            stack.ring_u,
            Size.parse(config.display_size),
            game_input=stack.input_path,
            worker_control=stack.control_path,
            registry=registry,
            on_upscaler_set=stack.remember_upscaler,
        )
        session_task = asyncio.create_task(session.run(stop), name="session")
        try:
            async with asyncio.timeout(CONNECT_TIMEOUT_S):
                await session.connected.wait()
        except TimeoutError:
            print("upcast up: the session could not publish to the relay", file=sys.stderr)
            return 1
        host = _browser_host(stream.host)
        # The player's token rides in the page URL; the page adds it to the relay URL.
        url = f"http://{host}:{endpoint.port}/?broadcast={stream.broadcast}&jwt={tokens.player}"
        extras = f"; session metrics http://{host}:{metrics_port}/metrics" if metrics_port else ""
        print(
            f"upcast is up: watch at {url}  (relay metrics http://{host}:{endpoint.port}/metrics"
            f"{extras}; Ctrl-C to stop)",
            flush=True,
        )
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CHECK_INTERVAL_S):
                    await stop.wait()
            stack.check_children()
            if relay.check():
                log.warning("relay restarted (restart #%d)", relay.restarts)
                session.reconnect()
            if session_task.done():
                session_task.result()  # surfaces the error
                break
            if deadline is not None and time.monotonic() >= deadline:
                log.info("duration of %.0f s reached: stopping", args.duration)
                break
    except RuntimeError as exc:  # the game died
        print(f"upcast up: {exc}", file=sys.stderr)
        code = 1
    except TimeoutError as exc:
        print(f"upcast up: {exc}", file=sys.stderr)
        code = 1
    finally:
        stop.set()
        if session_task is not None:
            with contextlib.suppress(Exception):
                await session_task
        stack.stop()
        relay.stop()
        key_dir.cleanup()
        log.info("upcast stopped; session %s cleaned up", config.name)
    return code
