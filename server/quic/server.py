"""WebTransport server over aioquic: accepts CONNECT :protocol webtransport.

Each accepted session is handed to `factory(session, request)`; everything else
(plain requests, CONNECT for other protocols, no common wt-protocol) is answered
with an HTTP error on that request stream only.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from aioquic._buffer import Buffer
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.asyncio.server import QuicServer
from aioquic.h3.connection import H3_ALPN
from aioquic.h3.events import HeadersReceived
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.connection import NetworkAddress, QuicConnection, QuicConnectionState
from aioquic.quic.packet import QuicPacketType, pull_quic_header

from . import sf
from .certs import CertBundle
from .congestion_register import default_algorithm
from .connection import IDLE_TIMEOUT_S, WtConnection, decode_headers, normalize_address
from .guard import (
    BAD_PATH,
    CONNECT_DEADLINE,
    H3_REQUEST_REJECTED,
    Admission,
    ConnectionGuard,
    GuardLimits,
    GuardLog,
    Violation,
    check_connect_path,
)
from .refusals import RefusalLog
from .session import Authorize, HandlerFactory, Refusal, WtRequest, WtSession

log = logging.getLogger(__name__)

DEFAULT_PROTOCOLS = ("moq-lite-03",)
SMALLEST_INITIAL_BYTES = 1200  # RFC 9000 14.1: aioquic opens no connection for less
SERVING_STATES = (QuicConnectionState.FIRSTFLIGHT, QuicConnectionState.CONNECTED)


@dataclass(frozen=True)
class WtServerOptions:
    factory: HandlerFactory
    protocols: tuple[str, ...] = DEFAULT_PROTOCOLS
    """Supported wt-protocol values; the client's order of preference decides."""
    allow_no_protocol: bool = False
    """Accept (200, no wt-protocol header) when nothing offered is supported."""
    wt_max_sessions: int = 1
    """SETTINGS_WT_MAX_SESSIONS to advertise (Safari needs >= 1); 0 sends none."""
    authorize: Authorize | None = None
    """Checked before the 200 and before any session state exists (see Authorize)."""
    refusal_log: RefusalLog = field(default_factory=RefusalLog)
    """Shared by every connection of the server: the rate limit is server-wide."""
    guard_limits: GuardLimits = field(default_factory=GuardLimits)
    guard_log: GuardLog = field(default_factory=GuardLog)
    """Counts (and logs, rate-limited) every connection the guard closed or refused."""
    admission: Admission | None = None
    """Set by serve_webtransport: which new connections are taken at all."""


def choose_protocol(offered: Sequence[str], supported: Sequence[str]) -> str | None:
    """First offered protocol the server supports (the client lists by preference)."""
    return next((p for p in offered if p in supported), None)


class WtServerConnection(WtConnection):
    def __init__(self, quic: QuicConnection, options: WtServerOptions, stream_handler: Any = None):
        super().__init__(quic, stream_handler)
        self._options = options
        self.wt_max_sessions = options.wt_max_sessions
        limits = options.guard_limits
        self.guard = ConnectionGuard(limits, self._loop.time())
        self.guard_log = options.guard_log
        self._max_field_section = limits.max_header_bytes
        self._accepted_any = False
        self._connect_deadline: asyncio.TimerHandle | None = self._loop.call_later(
            limits.connect_deadline_s, self._connect_deadline_passed
        )

    def _connect_deadline_passed(self) -> None:
        """A connection that has not had a CONNECT accepted in time is closed: holding
        state for peers that never ask for a session is what a flood wants."""
        self._connect_deadline = None
        if self._accepted_any or self._quic._state not in _OPEN_STATES:
            return
        limit = self._options.guard_limits.connect_deadline_s
        violation = Violation(CONNECT_DEADLINE, f"no CONNECT accepted within {limit:g} s")
        self.refuse_connection(violation, H3_REQUEST_REJECTED)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._connect_deadline is not None:
            self._connect_deadline.cancel()
            self._connect_deadline = None
        super().connection_lost(exc)

    def headers_received(self, event: HeadersReceived) -> None:
        stream_id = event.stream_id
        if stream_id in self.sessions:
            return  # trailers on a CONNECT stream: nothing to do
        assert self.guard is not None
        too_large = self.guard.check_headers(event.headers)
        if too_large is not None:
            self.refuse_connection(too_large)
            return
        headers = decode_headers(event.headers)
        method = headers.get(":method", "")
        if method != "CONNECT":
            self._refuse(stream_id, 404)
            return
        if headers.get(":protocol") != "webtransport":
            self._refuse(stream_id, 405)
            return
        if self.sessions and len(self.sessions) >= max(1, self.wt_max_sessions):
            self._refuse(stream_id, 429)  # the sessions per connection we advertised
            return
        offered = sf.parse_string_list(headers.get("wt-available-protocols", ""))
        chosen = choose_protocol(offered, self._options.protocols)
        if chosen is None and not self._options.allow_no_protocol:
            log.info("refusing WebTransport session: no common protocol in %s", offered)
            self._refuse(stream_id, 400)
            return
        path = headers.get(":path", "")
        bad_path = check_connect_path(path)
        if bad_path is not None:
            self._refuse_and_close(stream_id, 400, Violation(BAD_PATH, bad_path))
            return
        grant: object | None = None
        if self._options.authorize is not None:
            try:
                grant = self._options.authorize(path, headers)
            except Exception:
                log.exception("WebTransport authorize hook failed")
                grant = Refusal(500, "authorize hook failed")
            if isinstance(grant, Refusal):
                self._refuse_unauthorized(stream_id, grant)
                return

        reply = [(b":status", b"200"), (b"sec-webtransport-http3-draft", b"draft02")]
        if chosen is not None:
            reply.append((b"wt-protocol", sf.serialize_string(chosen).encode("ascii")))
        self.h3.send_headers(stream_id, reply)
        self.schedule_transmit()

        self._accepted_any = True
        if self._connect_deadline is not None:
            self._connect_deadline.cancel()
            self._connect_deadline = None
        self.guard.connect_accepted(stream_id)
        if self._options.admission is not None:
            self._options.admission.authenticated(self)
        session = WtSession(
            conn=self,
            session_id=stream_id,
            remote_address=self.remote_address,
            is_client=False,
            protocol=chosen,
        )
        self.sessions[stream_id] = session
        request = WtRequest(
            path=path,
            authority=headers.get(":authority", ""),
            headers=headers,
            protocol=chosen,
            remote_address=session.remote_address,
            grant=grant,
        )
        try:
            handler = self._options.factory(session, request)
        except Exception:
            log.exception("WebTransport handler factory failed")
            session.close(1, "internal error")
            return
        session.attach(handler)

    def _refuse_unauthorized(self, stream_id: int, refusal: Refusal) -> None:
        """Answer 401/403 and close the whole QUIC connection: its one use was this
        session, and a client that never closes (a flood) must not keep state here
        until the idle timeout."""
        host, port = self.remote_address
        self._options.refusal_log.refused(f"{host}:{port}", refusal.status, refusal.reason)
        self._refuse(stream_id, refusal.status)
        self._close_if_idle("unauthorized")

    def _refuse_and_close(self, stream_id: int, status: int, violation: Violation) -> None:
        """A malformed CONNECT: answer `status`, count and log it as the guard does,
        and close the connection unless it already carries a session."""
        host, port = self.remote_address
        self._options.guard_log.refused(f"{host}:{port}", violation, H3_REQUEST_REJECTED)
        self._refuse(stream_id, status)
        self._close_if_idle(violation.reason)

    def _close_if_idle(self, reason: str) -> None:
        if not self.sessions:
            self.transmit()  # the refusal leaves before CONNECTION_CLOSE
            self._quic.close(error_code=H3_REQUEST_REJECTED, reason_phrase=reason)
            self.schedule_transmit()

    def _refuse(self, stream_id: int, status: int) -> None:
        try:
            self.h3.send_headers(stream_id, [(b":status", str(status).encode())], end_stream=True)
        except Exception:  # the request stream may be half-gone already
            log.debug("could not refuse request on stream %d", stream_id, exc_info=True)
        self.schedule_transmit()


_OPEN_STATES = (QuicConnectionState.FIRSTFLIGHT, QuicConnectionState.CONNECTED)


class GuardedQuicServer(QuicServer):
    """aioquic's QuicServer with admission control in front of connection creation: an
    Initial that would open a connection over a limit (per source, unauthenticated in
    total, new connections per second per source) is dropped before aioquic allocates
    anything for it. Overrides `datagram_received` and `_connection_terminated` of the
    pinned aioquic (tests/test_quic_guard.py checks they are still called)."""

    def __init__(self, *, admission: Admission, guard_log: GuardLog, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.admission = admission
        self.guard_log = guard_log

    def datagram_received(self, data: bytes | str, addr: NetworkAddress) -> None:
        cid = self._new_connection_cid(data) if isinstance(data, bytes) else None
        if cid is None:
            super().datagram_received(data, addr)
            return
        host, port = normalize_address(addr)
        violation = self.admission.admit(host, self._loop.time())
        if violation is not None:
            # Dropped without an answer: a CONNECTION_CLOSE to a spoofed source would
            # make us an amplifier, and the client's retries cost one header parse each.
            self.guard_log.refused(f"{host}:{port}", violation)
            return
        super().datagram_received(data, addr)
        protocol = self._protocols.get(cid)
        if protocol is not None:
            self.admission.started(protocol, host, self._loop.time())

    def _new_connection_cid(self, data: bytes) -> bytes | None:
        """The destination CID of a datagram that would open a connection, else None."""
        if len(data) < SMALLEST_INITIAL_BYTES:
            return None
        try:
            header = pull_quic_header(
                Buffer(data=data), host_cid_length=self._configuration.connection_id_length
            )
        except ValueError:
            return None
        if (
            header.packet_type != QuicPacketType.INITIAL
            or header.destination_cid in self._protocols
        ):
            return None
        if header.version not in self._configuration.supported_versions:
            return None
        return header.destination_cid

    def _connection_terminated(self, protocol: QuicConnectionProtocol) -> None:
        self.admission.ended(protocol)
        super()._connection_terminated(protocol)


class WtServer:
    """A listening WebTransport endpoint. `port` is the bound UDP port."""

    def __init__(
        self,
        quic_server: QuicServer,
        transport: asyncio.DatagramTransport,
        refusal_log: RefusalLog | None = None,
        guard_log: GuardLog | None = None,
    ) -> None:
        self._quic_server = quic_server
        self.refusal_log = refusal_log or RefusalLog()
        self.guard_log = guard_log or GuardLog()
        self._transport = transport
        sockname = transport.get_extra_info("sockname")
        self.host: str = sockname[0]
        self.port: int = sockname[1]

    def connection_count(self) -> int:
        """QUIC connections the server still holds state for (draining ones included)."""
        return len(set(self._quic_server._protocols.values()))

    def serving_count(self) -> int:
        """QUIC connections not yet closing: the ones a deadline or limit has not ended.
        A closed connection stays in `connection_count` for its draining period (three
        probe timeouts, which grow with the RTT a loaded host measures)."""
        return sum(
            1
            for protocol in set(self._quic_server._protocols.values())
            if protocol._quic._state in SERVING_STATES
        )

    def close(self) -> None:
        """Close every connection (CONNECTION_CLOSE sent) and stop listening.

        Handlers get on_closed now: aioquic would only report the end after its
        draining timer, on a transport that is already closed.
        """
        for protocol in set(self._quic_server._protocols.values()):
            if isinstance(protocol, WtConnection):
                protocol.connection_lost_all("server closed")
        self._quic_server.close()


UDP_BUFFER_BYTES = 4 * 1024 * 1024


def grow_buffers(sock: socket.socket) -> None:
    """Ask for 4 MiB socket buffers: one event-loop stall at 200 Mbit/s of fan-out
    otherwise overflows the default ~200 KiB receive buffer, and every datagram the
    kernel drops costs a QUIC loss recovery (the kernel caps it at net.core.*mem_max)."""
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, option, UDP_BUFFER_BYTES)


def bind_udp(host: str, port: int) -> socket.socket:
    """A UDP socket; "::" also takes IPv4 (V6ONLY off) because Chromium resolves
    localhost to ::1 while other clients may use 127.0.0.1."""
    if ":" in host or host == "":
        sock = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        grow_buffers(sock)
        try:
            sock.bind((host or "::", port, 0, 0))
        except OSError:
            sock.close()
            raise
    else:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        grow_buffers(sock)
        try:
            sock.bind((host, port))
        except OSError:
            sock.close()
            raise
    sock.setblocking(False)
    return sock


def server_configuration(
    cert: CertBundle, idle_timeout: float = IDLE_TIMEOUT_S, congestion_control: str | None = None
) -> QuicConfiguration:
    config = QuicConfiguration(
        alpn_protocols=H3_ALPN,
        is_client=False,
        max_datagram_frame_size=65536,
        idle_timeout=idle_timeout,
        # upcast-media unless `upcast relay --congestion-control` chose reno/cubic
        congestion_control_algorithm=congestion_control or default_algorithm(),
    )
    config.load_cert_chain(cert.cert_path, cert.key_path)
    return config


async def serve_webtransport(
    factory: HandlerFactory,
    cert: CertBundle,
    *,
    host: str = "::",
    port: int = 4443,
    protocols: Sequence[str] = DEFAULT_PROTOCOLS,
    allow_no_protocol: bool = False,
    wt_max_sessions: int = 1,
    idle_timeout: float = IDLE_TIMEOUT_S,
    sock: socket.socket | None = None,
    authorize: Authorize | None = None,
    guard_limits: GuardLimits | None = None,
    guard_log: GuardLog | None = None,
) -> WtServer:
    """Listen for WebTransport on UDP `host`:`port` (or an already bound `sock`)."""
    limits = guard_limits or GuardLimits()
    admission = Admission(limits)
    options = WtServerOptions(
        factory=factory,
        protocols=tuple(protocols),
        allow_no_protocol=allow_no_protocol,
        wt_max_sessions=wt_max_sessions,
        authorize=authorize,
        guard_limits=limits,
        guard_log=guard_log or GuardLog(),
        admission=admission,
    )
    configuration = server_configuration(cert, idle_timeout)

    def create_protocol(quic: QuicConnection, stream_handler: Any = None) -> WtServerConnection:
        return WtServerConnection(quic, options, stream_handler)

    loop = asyncio.get_running_loop()
    transport, quic_server = await loop.create_datagram_endpoint(
        lambda: GuardedQuicServer(
            admission=admission,
            guard_log=options.guard_log,
            configuration=configuration,
            create_protocol=create_protocol,
        ),
        sock=sock if sock is not None else bind_udp(host, port),
    )
    return WtServer(quic_server, transport, options.refusal_log, options.guard_log)
