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
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from server.commands.link_flags import add_link_arguments
from server.commands.quality_flags import add_quality_arguments, quality_fields
from server.ops.browser_paths import WEB_ROOT
from server.stack.args import add_session_arguments, session_config_from

if TYPE_CHECKING:
    from server.auth.keys import AuthKey
    from server.stack.local import SessionConfig
    from server.stream_config import StreamConfig

log = logging.getLogger(__name__)


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
        "--audio",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="publish the game's sound as an Opus track (default: on; --no-audio: video only)",
    )
    add_link_arguments(parser)
    add_quality_arguments(parser)
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


def run(args: argparse.Namespace) -> int:
    from server.auth.keys import KeyFileError
    from server.auth.stack_key import stack_key
    from server.config_errors import validated
    from server.ops.event_loop import install_uvloop
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
        audio=args.audio,
        rate_control=args.rate_control,
        intra_refresh=args.intra_refresh,
        ladder=list(args.ladder),
        **quality_fields(args),
    )
    if config is None or stream is None:
        return 2
    install_uvloop()
    try:
        with stack_key(args.auth_key) as key:
            return asyncio.run(_main(args, config, stream, key))
    except KeyFileError as exc:
        print(f"upcast up: --auth-key: {exc}", file=sys.stderr)
        return 2


async def _main(
    args: argparse.Namespace,
    config: SessionConfig,
    stream: StreamConfig,
    key: tuple[Path, AuthKey],
) -> int:
    from server.auth.minting import session_tokens
    from server.quic.moq_link import with_token
    from server.relay.process import RelayProcess
    from server.serve.session_body import LiveSession, SessionPlan, run_game_session
    from server.stack.local import SourceStopped

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    key_path, auth_key = key
    tokens = session_tokens(auth_key, stream.broadcast)
    relay = RelayProcess(stream.host, stream.port, args.web_root, auth_key=key_path)
    code = 0
    try:
        try:
            endpoint = await loop.run_in_executor(None, relay.start)
        except (RuntimeError, TimeoutError) as exc:
            print(f"upcast up: relay failed to start on port {stream.port}: {exc}", file=sys.stderr)
            return 1
        host = _browser_host(stream.host)
        plan = SessionPlan(
            config=config,
            stream=stream,
            relay_url=f"http://{_session_host(stream.host)}:{endpoint.port}/",
            token=tokens.publisher,
            metrics_port=stream.session_metrics_port,
            duration_s=args.duration,
        )

        def announce(live: LiveSession) -> None:
            # The player's token rides in the page URL; the page adds it to the relay URL.
            url = with_token(
                f"http://{host}:{endpoint.port}/?broadcast={stream.broadcast}", tokens.player
            )
            port = live.metrics_port
            extras = f"; session metrics http://{host}:{port}/metrics" if port else ""
            print(
                f"upcast is up: watch at {url}  (relay metrics http://{host}:{endpoint.port}"
                f"/metrics{extras}; Ctrl-C to stop)",
                flush=True,
            )

        def check_relay(live: LiveSession) -> None:
            if relay.check():
                log.warning("relay restarted (restart #%d)", relay.restarts)
                live.session.reconnect()

        await run_game_session(plan, stop, on_up=announce, on_tick=check_relay)
    except SourceStopped as exc:  # the streamed application exited: its code is ours
        print(f"upcast up: {exc}", file=sys.stderr)
        code = 0 if exc.code == 0 else 1
    except (RuntimeError, TimeoutError) as exc:  # the game died, or the session never published
        print(f"upcast up: {exc}", file=sys.stderr)
        code = 1
    finally:
        relay.stop()
        log.info("upcast stopped; session %s cleaned up", config.name)
    return code
