"""The aioquic protocol object shared by the WebTransport server and client.

It owns the HTTP/3 layer of one QUIC connection, routes QUIC and HTTP/3 events
to the WtSession they belong to, and flushes the network once per loop
iteration however many writes the handlers made.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import pylsqpack
from aioquic._buffer import Buffer, BufferReadError
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.h3.connection import H3_ALPN, FrameType, H3Connection, H3Stream, Setting
from aioquic.h3.events import (
    DatagramReceived,
    DataReceived,
    H3Event,
    HeadersReceived,
    WebTransportStreamDataReceived,
)
from aioquic.quic.connection import QuicConnection
from aioquic.quic.events import (
    ConnectionTerminated,
    ProtocolNegotiated,
    QuicEvent,
    StopSendingReceived,
    StreamDataReceived,
    StreamReset,
)

from . import codes
from .guard import H3_EXCESSIVE_LOAD, ConnectionGuard, GuardLog, Violation
from .probe_backoff import cap_probe_backoff
from .session import Address, WtSession

log = logging.getLogger(__name__)

H3_INTERNAL_ERROR = 0x102
_PRUNE_AT = 4096
_MAX_CAPSULES = 2048  # a CLOSE capsule is at most 4 + 1024 bytes of body
SETTINGS_MAX_FIELD_SECTION_SIZE = 0x6


class _WtH3Connection(H3Connection):
    """H3Connection that also advertises SETTINGS_WT_MAX_SESSIONS.

    Safari does not open a WebTransport session without it and aioquic has no
    option for it; overriding the settings builder is the one hook it offers
    (it runs from H3Connection.__init__, so the flag is set before super()).
    """

    def __init__(
        self, quic: QuicConnection, wt_max_sessions: int, max_field_section: int | None = None
    ) -> None:
        self._wt_max_sessions = wt_max_sessions
        self._max_field_section = max_field_section
        super().__init__(quic, enable_webtransport=True)
        # No QPACK dynamic table (capacity 0, no blocked streams), as the settings just
        # sent say: a peer can then neither make one small header block expand to
        # megabytes by repeating a table entry nor park streams as "blocked" (aioquic
        # buffers those without bound). A WebTransport CONNECT is one small request.
        self._max_table_capacity = 0
        self._blocked_streams = 0
        self._decoder = pylsqpack.Decoder(0, 0)

    def create_webtransport_stream(self, session_id: int, is_unidirectional: bool = False) -> int:
        stream_id = super().create_webtransport_stream(session_id, is_unidirectional)
        if not is_unidirectional:
            # aioquic does not remember that a bidi stream it opened carries
            # WebTransport, so the peer's replies on it would be parsed as HTTP/3
            # frames (and fail). Mark it the way a peer-opened one is marked.
            stream = self._stream.get(stream_id)
            if stream is None:
                stream = self._stream[stream_id] = H3Stream(stream_id)
            stream.frame_type = FrameType.WEBTRANSPORT_STREAM
            stream.session_id = session_id
        return stream_id

    # The guard needs aioquic's record of the stream a packet was for, also when
    # aioquic dropped it from `_stream` while handling that packet (a peer's
    # unidirectional stream is dropped as soon as its FIN arrives): both receive paths
    # are handed that record, so they note it here.
    received_stream: H3Stream | None = None

    def _receive_request_or_push_data(
        self, stream: H3Stream, data: bytes, stream_ended: bool
    ) -> list[H3Event]:
        self.received_stream = stream
        return super()._receive_request_or_push_data(stream, data, stream_ended)

    def _receive_stream_data_uni(
        self, stream: H3Stream, data: bytes, stream_ended: bool
    ) -> list[H3Event]:
        self.received_stream = stream
        return super()._receive_stream_data_uni(stream, data, stream_ended)

    def forget_stream(self, stream_id: int) -> None:
        """Drop aioquic's HTTP/3 state of a finished WebTransport stream.

        aioquic frees an H3Stream only when both halves ended at the HTTP/3 layer,
        which never happens for WebTransport streams written through QUIC directly;
        without this a long relay session would keep one object per stream forever.
        """
        self._stream.pop(stream_id, None)

    def _get_local_settings(self) -> dict[int, int]:
        settings = super()._get_local_settings()
        settings[Setting.QPACK_MAX_TABLE_CAPACITY] = 0
        settings[Setting.QPACK_BLOCKED_STREAMS] = 0
        if self._max_field_section is not None:
            settings[SETTINGS_MAX_FIELD_SECTION_SIZE] = self._max_field_section
        if self._wt_max_sessions > 0:
            settings[codes.SETTINGS_WT_MAX_SESSIONS] = self._wt_max_sessions
        return settings


def normalize_address(addr: Any) -> Address:
    """(host, port) from an aioquic address; '::ffff:1.2.3.4' becomes '1.2.3.4'."""
    if not addr:
        return ("", 0)
    host = str(addr[0])
    if host.startswith("::ffff:") and "." in host:
        host = host[len("::ffff:") :]
    return (host, int(addr[1]))


def decode_headers(raw: list[tuple[bytes, bytes]]) -> dict[str, str]:
    out: dict[str, str] = {}
    for name_b, value_b in raw:
        name = name_b.decode("latin-1").lower()
        value = value_b.decode("latin-1")
        out[name] = f"{out[name]}, {value}" if name in out else value
    return out


def close_reason(capsules: bytes) -> str:
    """'closed by peer: CODE REASON' from a CLOSE_WEBTRANSPORT_SESSION capsule, if any."""
    buf = Buffer(data=capsules)
    try:
        while not buf.eof():
            kind = buf.pull_uint_var()
            body = buf.pull_bytes(buf.pull_uint_var())
            if kind == codes.CLOSE_WEBTRANSPORT_SESSION and len(body) >= 4:
                code = int.from_bytes(body[:4], "big")
                text = body[4:].decode("utf-8", "replace")
                return f"closed by peer: {code} {text}".strip()
    except BufferReadError:
        pass
    return "closed by peer"


# Both ends detect a silent peer within this; PINGs every KEEPALIVE_S keep live ones.
IDLE_TIMEOUT_S = 10.0
KEEPALIVE_S = 2.5


class WtConnection(QuicConnectionProtocol):
    """Base protocol: subclasses implement `headers_received` (request or response)."""

    wt_max_sessions = 1

    def __init__(self, quic: QuicConnection, stream_handler: Any = None) -> None:
        super().__init__(quic, stream_handler)
        # Live media: after an outage the next probe is at most 0.5 s away (probe_backoff.py).
        cap_probe_backoff(quic)
        self._h3: _WtH3Connection | None = None
        self.sessions: dict[int, WtSession] = {}
        self._stream_owner: dict[int, WtSession] = {}
        self._flush_handle: asyncio.Handle | None = None
        self._prune_at = _PRUNE_AT
        # A peer that vanishes without CONNECTION_CLOSE (a killed relay, a closed
        # laptop) is only noticed by the idle timeout; keepalive PINGs keep a quiet but
        # live connection under it, so the timeout can be short (IDLE_TIMEOUT_S).
        self._keepalive_handle: asyncio.TimerHandle | None = self._loop.call_later(
            KEEPALIVE_S, self._keepalive
        )
        # Server side: the bounds on what the peer may send besides WebTransport payload
        # (guard.py). Once one is crossed nothing more of this peer reaches HTTP/3.
        self.guard: ConnectionGuard | None = None
        self.guard_log: GuardLog | None = None
        self.guard_tripped: Violation | None = None

    # --- helpers used by WtSession -------------------------------------------

    @property
    def quic(self) -> QuicConnection:
        return self._quic

    @property
    def h3(self) -> _WtH3Connection:
        if self._h3 is None:
            raise ConnectionError("HTTP/3 is not negotiated yet")
        return self._h3

    @property
    def remote_address(self) -> Address:
        return normalize_address(self._quic.get_peer_address())

    def schedule_transmit(self) -> None:
        """Coalesce: many sends in one callback become one datagrams_to_send pass."""
        if self._flush_handle is None:
            self._flush_handle = self._loop.call_soon(self._flush)

    def _flush(self) -> None:
        self._flush_handle = None
        self.transmit()

    def transmit(self) -> None:
        # Every network write passes here (timers and received datagrams included):
        # resets held back while their stream was over the peer's MAX_STREAMS go out
        # once aioquic has unblocked the stream (WtSession.reset_stream).
        for session in self.sessions.values():
            session.flush_deferred_resets()
        super().transmit()

    def _keepalive(self) -> None:
        self._keepalive_handle = None
        if self._closed.is_set():
            return
        self._quic.send_ping(0)
        self.transmit()
        self._keepalive_handle = self._loop.call_later(KEEPALIVE_S, self._keepalive)

    def register_stream(self, stream_id: int, session: WtSession) -> None:
        self._stream_owner[stream_id] = session
        if len(self._stream_owner) > self._prune_at:
            self.prune_streams()

    def prune_streams(self) -> None:
        """Forget streams aioquic has discarded (both directions done)."""
        for sid in [s for s in self._stream_owner if self.stream_discarded(s)]:
            owner = self._stream_owner.pop(sid)
            owner.forget_stream(sid)
            if self._h3 is not None:
                self._h3.forget_stream(sid)
        # Amortised: the next prune waits until the map has doubled.
        self._prune_at = max(_PRUNE_AT, 2 * len(self._stream_owner))

    def stream_discarded(self, stream_id: int) -> bool:
        """Whether aioquic has forgotten a stream it once had (fully finished)."""
        return self._quic._stream_is_discarded(stream_id)

    def session_ended(self, session: WtSession, reason: str, *, local: bool) -> None:
        """Drop a session; with none left on this connection, close the connection
        (after flushing, so a close capsule goes out before CONNECTION_CLOSE)."""
        if self.sessions.pop(session.session_id, None) is None and session.closed:
            return
        for sid in [s for s, owner in self._stream_owner.items() if owner is session]:
            del self._stream_owner[sid]
        session.mark_closed(reason)
        if not self.sessions:
            self.transmit()
            self._quic.close(error_code=codes.H3_NO_ERROR, reason_phrase=reason[:100])
            self.schedule_transmit()

    # --- event routing -------------------------------------------------------

    def quic_event_received(self, event: QuicEvent) -> None:
        try:
            self._route(event)
        except Exception:
            # Whatever a peer sends, an unexpected state kills this connection only.
            log.exception("WebTransport connection failed; closing it")
            self._quic.close(error_code=H3_INTERNAL_ERROR, reason_phrase="internal error")
            self.schedule_transmit()

    def _route(self, event: QuicEvent) -> None:
        if isinstance(event, ProtocolNegotiated):
            if self._h3 is None and event.alpn_protocol in H3_ALPN:
                self._h3 = _WtH3Connection(self._quic, self.wt_max_sessions)
        elif isinstance(event, StreamReset):
            self._stream_aborted(event.stream_id, event.error_code, stop_sending=False)
        elif isinstance(event, StopSendingReceived):
            self._stream_aborted(event.stream_id, event.error_code, stop_sending=True)
        elif isinstance(event, ConnectionTerminated):
            reason = f"connection closed: {event.error_code:#x} {event.reason_phrase}".strip()
            self.connection_lost_all(reason)
        if self._h3 is None or self.guard_tripped is not None:
            return
        self._h3.received_stream = None
        h3_events = self._h3.handle_event(event)
        if self.guard is not None and isinstance(event, StreamDataReceived):
            violation = self.guard.after_stream_data(
                self._h3.received_stream,
                event.stream_id,
                len(event.data),
                self.sessions,
                now=self._loop.time(),
            )
            if violation is not None:
                self.refuse_connection(violation)
                return
        for h3_event in h3_events:
            self._h3_event(h3_event)

    def refuse_connection(self, violation: Violation, code: int = H3_EXCESSIVE_LOAD) -> None:
        """Close the whole connection for crossing a guard limit: counted, logged
        (rate-limited), its sessions told at once, nothing more it sends is parsed."""
        if self.guard_tripped is not None:
            return
        self.guard_tripped = violation
        if self.guard_log is not None:
            host, port = self.remote_address
            self.guard_log.refused(f"{host}:{port}", violation, code)
        self.connection_lost_all(f"refused: {violation.reason}")
        self._quic.close(error_code=code, reason_phrase=violation.reason)
        self.schedule_transmit()

    def _h3_event(self, event: H3Event) -> None:
        if isinstance(event, WebTransportStreamDataReceived):
            session = self.sessions.get(event.session_id)
            if session is None:
                return  # a stream for a session we never accepted: ignore its data
            if event.stream_id not in self._stream_owner:
                self.register_stream(event.stream_id, session)
            session.deliver_data(event.stream_id, event.data, event.stream_ended)
        elif isinstance(event, DatagramReceived):
            session = self.sessions.get(event.stream_id)
            if session is not None:
                session.deliver_datagram(event.data)
        elif isinstance(event, HeadersReceived):
            self.headers_received(event)
        elif isinstance(event, DataReceived):
            session = self.sessions.get(event.stream_id)
            if session is None:
                return
            # Capsules on the CONNECT stream; its end (FIN) ends the session.
            if len(session.capsules) < _MAX_CAPSULES:
                session.capsules += event.data[: _MAX_CAPSULES - len(session.capsules)]
            if event.stream_ended:
                self.session_ended(session, close_reason(bytes(session.capsules)), local=False)

    def _stream_aborted(self, stream_id: int, error_code: int, *, stop_sending: bool) -> None:
        session = self.sessions.get(stream_id)
        if session is not None:
            self.session_ended(session, "CONNECT stream aborted by peer", local=False)
            return
        owner = self._stream_owner.get(stream_id)
        if owner is not None:
            owner.deliver_reset(stream_id, error_code, stop_sending)

    def connection_lost_all(self, reason: str) -> None:
        for session in list(self.sessions.values()):
            self.sessions.pop(session.session_id, None)
            session.mark_closed(reason)
        self._stream_owner.clear()

    def headers_received(self, event: HeadersReceived) -> None:
        """The one hook of each side: the server answers a CONNECT request
        (server.py), the client reads the CONNECT response (client.py). Both
        subclasses implement it; this base is never instantiated."""
        raise NotImplementedError
