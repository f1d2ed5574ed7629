"""``upcast session``: stream an existing game session's ring U to a relay.

``upcast up`` runs this in its own process next to the game and worker it
starts; on its own it attaches to rings made by someone else (an engine that
produces into ring U, a session manager) and publishes to any moq-lite relay.
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

if TYPE_CHECKING:
    from server.stream_config import StreamConfig

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ring", required=True, help="ring U name (display frames) to stream")
    parser.add_argument(
        "--relay", required=True, help="relay URL, e.g. http://localhost:4443/ (hash fetched)"
    )
    parser.add_argument("--cert-sha256", default=None, help="pin this certificate hash instead")
    parser.add_argument("--broadcast", default="game", help="broadcast name (default: game)")
    parser.add_argument("--fps", type=float, default=60.0, help="stream frame rate")
    parser.add_argument("--bitrate-kbps", type=int, default=None, help="video bitrate")
    parser.add_argument("--gop-seconds", type=float, default=2.0, help="keyframe interval")
    parser.add_argument(
        "--audio",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="publish the game's sound as an Opus track (default: on; --no-audio: video only)",
    )
    add_link_arguments(parser)
    add_quality_arguments(parser)
    parser.add_argument("--game-input", type=Path, default=None, help="game input socket")
    parser.add_argument("--worker-control", type=Path, default=None, help="worker control socket")
    parser.add_argument("--metrics-port", type=int, default=0, help="Prometheus port (0 = off)")
    parser.add_argument("--duration", type=float, default=None, help="stop after SECONDS")
    parser.add_argument(
        "--attach-timeout", type=float, default=10.0, help="seconds to wait for the ring"
    )
    token = parser.add_mutually_exclusive_group()
    token.add_argument(
        "--token", default=None, help="publish token for the relay (upcast token sign ...)"
    )
    token.add_argument(
        "--token-file",
        type=Path,
        default=None,
        help="read the publish token from this file (keeps it out of the process list)",
    )


def run(args: argparse.Namespace) -> int:
    from server.config_errors import validated
    from server.stream_config import StreamConfig

    # Same field rules as upcast up (broadcast name, bitrate, gop, metrics port).
    stream = validated(
        StreamConfig,
        "session",
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
    if stream is None:
        return 2
    if not 0 < args.fps <= 240:
        print(f"upcast session: --fps must be in (0, 240], got {args.fps}", file=sys.stderr)
        return 2
    if not args.relay.startswith(("http://", "https://")):
        print(
            f"upcast session: --relay must be an http(s):// URL, got {args.relay}", file=sys.stderr
        )
        return 2
    if args.token_file is not None:
        try:
            args.token = args.token_file.read_text().strip()
        except OSError as exc:
            problem = exc.strerror or exc
            print(f"upcast session: --token-file {args.token_file}: {problem}", file=sys.stderr)
            return 2
        if not args.token:
            print(f"upcast session: --token-file {args.token_file} is empty", file=sys.stderr)
            return 2
    from server.ops.event_loop import install_uvloop

    install_uvloop()
    return asyncio.run(_main(args, stream))


async def _main(args: argparse.Namespace, stream: StreamConfig) -> int:
    from prometheus_client import CollectorRegistry, start_http_server

    from server.frames.frame import Size
    from server.frames.ring import RingError
    from server.frames.ring_frames import attach_display_ring
    from server.session.runner import StreamingSession, StreamSettings

    try:
        ring = attach_display_ring(args.ring, wait_s=args.attach_timeout)
    except (RingError, FileNotFoundError, TimeoutError) as exc:
        print(f"upcast session: cannot attach ring U {args.ring!r}: {exc}", file=sys.stderr)
        return 1
    display = Size(ring.max_width, ring.max_height)
    registry = CollectorRegistry()
    if args.metrics_port:
        start_http_server(args.metrics_port, registry=registry)
    session = StreamingSession(
        StreamSettings(
            relay_url=args.relay,
            broadcast=args.broadcast,
            fps=args.fps,
            bitrate=stream.bitrate_bps,
            gop_seconds=args.gop_seconds,
            cert_hash_hex=args.cert_sha256,
            token=args.token,
            audio=stream.audio,
            rate_control=stream.rate_control,
            intra_refresh=stream.intra_refresh,
            ladder=tuple(stream.ladder),
            quality=stream.quality,
            quality_preference=stream.quality_preference,
            min_scale=stream.min_scale,
            max_scale=stream.max_scale,
            quality_methods=tuple(stream.quality_methods),
        ),
        ring,
        display,
        game_input=args.game_input,
        worker_control=args.worker_control,
        registry=registry,
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.duration is not None:
        loop.call_later(args.duration, stop.set)
    log.info("streaming ring %s (%s) to %s as %r", args.ring, display, args.relay, args.broadcast)
    try:
        await session.run(stop)
    finally:
        ring.close()
    return 0
