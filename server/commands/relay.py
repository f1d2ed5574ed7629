"""``upcast relay``: the moq-lite relay (WebTransport on UDP, HTTP on TCP, one port)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from server.moq.limits import IngressLimits
from server.ops.browser_paths import WEB_ROOT
from server.quic.guard import GuardLimits

if TYPE_CHECKING:
    from server.auth import Authorizer
    from server.quic.certs import CertBundle
    from server.relay.settings import RelaySettings

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--host", default="::", help="address to bind (default :: = all, dual stack)"
    )
    parser.add_argument("--port", type=int, default=4443, help="UDP (QUIC) and TCP (HTTP) port")
    parser.add_argument(
        "--web-root",
        type=Path,
        default=None,
        help=f"static web client to serve (default: {WEB_ROOT} if built)",
    )
    parser.add_argument(
        "--cert", type=Path, default=None, help="certificate PEM (default: generated)"
    )
    parser.add_argument("--key", type=Path, default=None, help="private key PEM for --cert")
    parser.add_argument(
        "--max-backlog-kib",
        type=int,
        default=2048,
        help="bytes queued for one viewer before it skips to the newest group (KiB)",
    )
    parser.add_argument(
        "--max-latency-ms",
        type=int,
        default=500,
        help="lag after which a viewer that set no max_latency skips to the newest group"
        " (0 = only the backlog limit)",
    )
    parser.add_argument("--max-sessions", type=int, default=1000, help="sessions at once")
    parser.add_argument(
        "--auth-key",
        type=Path,
        default=None,
        help="key file (JWK) that publish/subscribe tokens are verified with"
        " (make one: upcast token generate --key PATH)",
    )
    parser.add_argument(
        "--public-viewers",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="sessions without a token may watch (never publish or send inputs)",
    )
    parser.add_argument(
        "--no-auth",
        action="store_true",
        help="open relay for local development: anyone may publish (logs a warning)",
    )
    parser.add_argument(
        "--viewer-upload-kib-s",
        type=int,
        default=IngressLimits().viewer_bytes_per_s // 1024,
        help="bytes/s a session without publish rights may send before it is closed (KiB)",
    )
    parser.add_argument(
        "--publisher-upload-mib-s",
        type=int,
        default=IngressLimits().publisher_bytes_per_s // (1024 * 1024),
        help="bytes/s a publishing session may send before it is closed (MiB)",
    )
    guard = GuardLimits()
    parser.add_argument(
        "--max-connections-per-source",
        type=int,
        default=guard.max_connections_per_source,
        help="QUIC connections open at once from one IP address (default: %(default)s)",
    )
    parser.add_argument(
        "--new-connections-per-s",
        type=float,
        default=guard.new_connections_per_s_per_source,
        help="new QUIC connections per second from one IP address, burst twice that"
        " (default: %(default)s)",
    )
    parser.add_argument(
        "--connect-deadline-s",
        type=float,
        default=guard.connect_deadline_s,
        help="seconds a connection has to get its WebTransport CONNECT accepted"
        " (default: %(default)s)",
    )
    parser.add_argument(
        "--congestion-control",
        default="upcast-media",
        help="QUIC congestion controller: upcast-media (holds the rate under random loss),"
        " reno or cubic (default: %(default)s)",
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after SECONDS")
    parser.add_argument("--ready-file", type=Path, default=None, help=argparse.SUPPRESS)


def _settings(args: argparse.Namespace) -> RelaySettings | None:
    """The flags as a RelaySettings, or None after printing which field is wrong."""
    from server.config_errors import validated
    from server.relay.settings import RelaySettings

    fields = {name: getattr(args, name) for name in RelaySettings.model_fields}
    return validated(RelaySettings, "relay", **fields)


def _authorizer(settings: RelaySettings) -> Authorizer:
    """Raises KeyFileError (it names the file) for a missing or malformed key."""
    from server.auth import Authorizer, load_key

    if settings.auth_key is None:
        log.warning("relay: --no-auth: anyone may publish and send inputs")
        return Authorizer.open_relay()
    return Authorizer(load_key(settings.auth_key), public_viewers=settings.public_viewers)


def run(args: argparse.Namespace) -> int:
    from server.auth import KeyFileError

    settings = _settings(args)
    if settings is None:
        return 2
    try:
        authorizer = _authorizer(settings)
    except KeyFileError as exc:
        print(f"upcast relay: --auth-key: {exc}", file=sys.stderr)
        return 2
    from server.ops.event_loop import install_uvloop

    install_uvloop()
    return asyncio.run(_main(args, settings, authorizer))


async def _main(args: argparse.Namespace, settings: RelaySettings, auth: Authorizer) -> int:
    from server.quic.certs import generate_cert, load_cert

    with tempfile.TemporaryDirectory(prefix="upcast-cert-") as cert_dir:
        # A generated key lives only as long as this relay: never left in /tmp.
        if settings.cert is not None and settings.key is not None:
            cert = load_cert(settings.cert, settings.key)
        else:
            cert = generate_cert(directory=cert_dir)
        return await _serve(args, settings, auth, cert)


async def _serve(
    args: argparse.Namespace, settings: RelaySettings, auth: Authorizer, cert: CertBundle
) -> int:
    from server.quic.congestion_register import set_default_algorithm
    from server.relay.relay import Relay, RelayConfig

    set_default_algorithm(settings.congestion_control)  # every QUIC connection of this relay

    web_root = settings.web_root
    if web_root is None and (WEB_ROOT / "index.html").is_file():
        web_root = WEB_ROOT
    config = RelayConfig(
        host=settings.host,
        port=settings.port,
        web_root=web_root,
        max_backlog_bytes=settings.max_backlog_kib * 1024,
        default_max_latency_ms=settings.max_latency_ms,
        max_connections=settings.max_sessions,
        authorizer=auth,
        ingress=settings.ingress(),
        guard=settings.guard(),
    )
    relay = Relay(config, cert)
    try:
        await relay.start()
    except OSError as exc:
        print(
            f"upcast relay: cannot listen on port {settings.port}: {exc.strerror or exc}",
            file=sys.stderr,
        )
        return 1
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    host = "localhost" if settings.host in ("::", "0.0.0.0", "") else settings.host
    print(
        f"upcast relay: listening on port {relay.port}; certificate sha256 {cert.sha256_hex}; "
        f"page http://{host}:{relay.port}/ ; metrics http://{host}:{relay.port}/metrics",
        flush=True,
    )
    if args.ready_file is not None:
        args.ready_file.write_text(f"{relay.port}\n{cert.sha256_hex}\n")
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(args.duration):
            await stop.wait()
    await relay.close()
    log.info("relay stopped")
    return 0
