"""WebTransport client over aioquic (the Python publisher, load-test viewers, tests).

Certificate pinning: aioquic has no hook to check a certificate by hash during the
handshake, so with `cert_hash_hex` CA verification is turned off and the peer's
leaf certificate (`QuicConnection.tls._peer_certificate`, private but the only
place aioquic keeps it) is hashed right after the handshake, before any request
is sent; a mismatch closes the connection and raises CertificateHashError.
"""

from __future__ import annotations

import asyncio
import hmac
import socket
import ssl
from collections.abc import Sequence
from typing import Any
from urllib.parse import urlsplit

from aioquic.h3.connection import H3_ALPN
from aioquic.h3.events import HeadersReceived
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.connection import QuicConnection
from aioquic.quic.events import ConnectionTerminated, QuicEvent
from cryptography.hazmat.primitives import serialization

from server.ops.redact import redact_url

from . import codes, sf
from .certs import der_sha256_hex
from .congestion_register import default_algorithm
from .connection import IDLE_TIMEOUT_S, WtConnection, decode_headers
from .http_fetch import fetch_cert_hash
from .server import grow_buffers
from .session import HandlerFactory, WtRequest, WtSession

DEFAULT_PROTOCOLS = ("moq-lite-03",)


class WtConnectError(ConnectionError):
    """The WebTransport session could not be established (reason in the message).

    The message names the URL with its ``?jwt=`` token masked (server.ops.redact): it
    is logged by every caller that retries."""


class CertificateHashError(WtConnectError):
    """The server's certificate does not have the pinned SHA-256."""


class WtClientConnection(WtConnection):
    def __init__(self, quic: QuicConnection, stream_handler: Any = None) -> None:
        super().__init__(quic, stream_handler)
        self.responses: dict[int, asyncio.Future[dict[str, str]]] = {}
        self.close_reason = ""

    def headers_received(self, event: HeadersReceived) -> None:
        waiter = self.responses.pop(event.stream_id, None)
        if waiter is not None and not waiter.done():
            waiter.set_result(decode_headers(event.headers))

    def session_ended(self, session: WtSession, reason: str, *, local: bool) -> None:
        super().session_ended(session, reason, local=local)
        if not self.sessions:
            # CONNECTION_CLOSE is flushed by the transmit queued just before this;
            # a client need not linger in the draining state (RFC 9000 10.2), and
            # freeing the socket now means no leak when the caller's loop ends.
            self._loop.call_soon(self.abort)

    def abort(self) -> None:
        """Close the QUIC connection (if still open), flush, release the socket."""
        self._quic.close(error_code=codes.H3_NO_ERROR)
        self.transmit()
        if self._transport is not None:
            self._transport.close()

    def quic_event_received(self, event: QuicEvent) -> None:
        if isinstance(event, ConnectionTerminated):
            self.close_reason = f"{event.error_code:#x} {event.reason_phrase}".strip()
        super().quic_event_received(event)
        if isinstance(event, ConnectionTerminated):
            for waiter in self.responses.values():
                if not waiter.done():
                    waiter.set_exception(WtConnectError(f"connection closed: {self.close_reason}"))
            self.responses.clear()
            # The socket is ours (one per client connection): release it.
            if self._transport is not None:
                self._loop.call_soon(self._transport.close)


def _split_url(url: str) -> tuple[str, str, int, str]:
    parts = urlsplit(url)
    if parts.scheme not in ("https", "http") or not parts.hostname:
        raise ValueError(f"not an http(s) URL: {redact_url(url)!r}")
    port = parts.port or 443
    path = parts.path or "/"
    if parts.query:
        path += "?" + parts.query
    return parts.scheme, parts.hostname, port, path


async def _open(host: str, port: int, config: QuicConfiguration) -> WtClientConnection:
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    addr: tuple[Any, ...] = infos[0][4]
    if len(addr) == 2:
        # One dual-stack socket serves both families (as aioquic's own client does).
        addr = ("::ffff:" + addr[0], addr[1], 0, 0)
    sock = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        grow_buffers(sock)  # a publisher's burst or a viewer's stall must not drop datagrams
        sock.bind(("::", 0, 0, 0))
    except OSError:
        sock.close()
        raise
    quic = QuicConnection(configuration=config)
    _, protocol = await loop.create_datagram_endpoint(lambda: WtClientConnection(quic), sock=sock)
    protocol.connect(addr)
    return protocol


async def connect(
    url: str,
    *,
    factory: HandlerFactory,
    protocols: Sequence[str] = DEFAULT_PROTOCOLS,
    cert_hash_hex: str | None = None,
    verify: bool = True,
    origin: str | None = None,
    timeout: float = 10.0,
    congestion_control: str | None = None,
) -> tuple[WtSession, str | None]:
    """Open a WebTransport session to `url` and attach `factory(session, request)`.

    `https://` URLs connect directly. An `http://` URL without `cert_hash_hex`
    first GETs /certificate.sha256 on the same port over TCP and pins it, as
    @moq/watch does. Returns the session and the server's `wt-protocol`.
    """
    scheme, host, port, path = _split_url(url)
    shown = redact_url(url)  # the URL as error messages name it: its token masked
    if scheme == "http" and cert_hash_hex is None:
        cert_hash_hex = await fetch_cert_hash(host, port, timeout=timeout)
    authority = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    config = QuicConfiguration(
        alpn_protocols=H3_ALPN,
        is_client=True,
        max_datagram_frame_size=65536,
        server_name=host,
        idle_timeout=IDLE_TIMEOUT_S,  # a vanished relay is noticed in seconds, not a minute
        # publishers and load-test viewers send media too: same controller as the relay
        congestion_control_algorithm=congestion_control or default_algorithm(),
    )
    if cert_hash_hex is not None or not verify:
        config.verify_mode = ssl.CERT_NONE

    stage = "QUIC handshake"
    protocol: WtClientConnection | None = None
    try:
        async with asyncio.timeout(timeout):
            protocol = await _open(host, port, config)
            try:
                await protocol.wait_connected()
            except ConnectionError:
                raise WtConnectError(
                    f"QUIC handshake with {authority} failed: {protocol.close_reason}"
                ) from None
            if cert_hash_hex is not None:
                _check_cert_hash(protocol, cert_hash_hex, authority)

            stage = "CONNECT"
            session_id = protocol.quic.get_next_available_stream_id()
            session = WtSession(
                conn=protocol,
                session_id=session_id,
                remote_address=protocol.remote_address,
                is_client=True,
            )
            protocol.sessions[session_id] = session
            waiter = asyncio.get_running_loop().create_future()
            protocol.responses[session_id] = waiter
            headers = [
                (b":method", b"CONNECT"),
                (b":scheme", b"https"),
                (b":authority", authority.encode()),
                (b":path", path.encode()),
                (b":protocol", b"webtransport"),
                (b"origin", (origin or f"https://{authority}").encode()),
            ]
            if protocols:
                offer = ", ".join(sf.serialize_string(p) for p in protocols)
                headers.append((b"wt-available-protocols", offer.encode("ascii")))
            protocol.h3.send_headers(session_id, headers)
            protocol.transmit()
            response: dict[str, str] = await waiter
    except TimeoutError:
        if protocol is not None:
            protocol.abort()
        raise WtConnectError(
            f"WebTransport connect to {shown} timed out after {timeout:g}s during {stage}"
        ) from None
    except BaseException:
        if protocol is not None:
            protocol.abort()
        raise

    status = response.get(":status", "")
    chosen = sf.parse_string(response.get("wt-protocol", "")) if "wt-protocol" in response else None
    if status != "200" or (chosen is not None and protocols and chosen not in protocols):
        protocol.abort()
        raise WtConnectError(
            f"WebTransport CONNECT to {shown} refused: "
            f"status {status or '?'}, wt-protocol {chosen!r}"
        )
    session.protocol = chosen
    request = WtRequest(
        path=path,
        authority=authority,
        headers=response,
        protocol=chosen,
        remote_address=session.remote_address,
    )
    try:
        handler = factory(session, request)
    except BaseException:
        session.close(1, "handler factory failed")
        raise
    session.attach(handler)
    return session, chosen


def _check_cert_hash(protocol: WtClientConnection, expected_hex: str, authority: str) -> None:
    peer = protocol.quic.tls._peer_certificate
    actual = der_sha256_hex(peer.public_bytes(serialization.Encoding.DER)) if peer else ""
    expected = expected_hex.strip().lower()
    if not hmac.compare_digest(actual, expected):
        # 0x12a: CRYPTO_ERROR carrying TLS alert 42 (bad_certificate).
        protocol.close(error_code=0x12A, reason_phrase="certificate hash mismatch")
        protocol.abort()
        raise CertificateHashError(
            f"certificate of {authority} has SHA-256 {actual or '(none)'}, expected {expected}"
        )


__all__ = [
    "CertificateHashError",
    "WtConnectError",
    "connect",
    "fetch_cert_hash",
]
