"""One WebTransport session as the protocol code sees it, on either side.

WtSession is the object handed to a handler: it turns the sans-IO outputs
(send, reset, stop sending, close) into aioquic calls and keeps the rules that
aioquic leaves to the caller: no write after the peer stopped or reset a stream,
no RESET_STREAM for a stream the peer has not yet let us open, error codes mapped
into the HTTP/3 space, one network flush per loop iteration.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from aioquic.buffer import encode_uint_var
from aioquic.h3.connection import H3Connection
from aioquic.quic.connection import QuicConnection, stream_is_unidirectional

from . import codes

log = logging.getLogger(__name__)

Address = tuple[str, int]


@dataclass(frozen=True)
class WtRequest:
    """The CONNECT request behind a session.

    On the server: what the client asked for. On the client: what was asked, with
    `headers` holding the server's response headers instead.
    """

    path: str
    authority: str
    headers: dict[str, str]
    """Lowercase names; repeated fields joined with ", "; values decoded as latin-1."""
    protocol: str | None
    """The negotiated `wt-protocol`, or None when the session has none."""
    remote_address: Address
    """Peer (host, port); IPv4-mapped IPv6 addresses are shown as plain IPv4."""
    grant: object | None = None
    """On the server: what the `authorize` hook granted this session (None: no hook)."""


@dataclass(frozen=True, slots=True)
class Refusal:
    """An `authorize` hook's "no": the HTTP status for the CONNECT and a short reason
    for the log (never echoed to the peer)."""

    status: int
    reason: str


Authorize = Callable[[str, dict[str, str]], object]
"""``authorize(request_path, headers)`` -> a Refusal, or the grant to attach to the
session's WtRequest. Runs before the server answers 200 or allocates the session."""


class WtSessionHandler(Protocol):
    """What the protocol code implements. Callbacks run on the event loop thread.

    A handler may also define `on_datagram(self, data: bytes) -> None`; datagrams
    are dropped for handlers without it.
    """

    def on_stream_data(self, stream_id: int, data: bytes, end_stream: bool) -> None: ...

    def on_stream_reset(self, stream_id: int, code: int) -> None:
        """The peer reset its sending side (RESET_STREAM) or asked us to stop
        (STOP_SENDING). `code` is the WebTransport application code."""

    def on_closed(self, reason: str) -> None:
        """Called exactly once, whoever ended the session and however."""


HandlerFactory = Callable[["WtSession", WtRequest], WtSessionHandler]


@dataclass
class _StreamState:
    # Our sending side is gone (STOP_SENDING received or we reset it): drop writes.
    send_closed: bool = False


class SessionConnection(Protocol):
    """What a session needs of its connection; ``connection.WtConnection`` is the one
    implementation (an interface here, so this module does not import connection.py,
    which imports this one)."""

    _transport: asyncio.DatagramTransport | None

    @property
    def quic(self) -> QuicConnection: ...

    @property
    def h3(self) -> H3Connection: ...

    def schedule_transmit(self) -> None: ...

    def register_stream(self, stream_id: int, session: WtSession) -> None: ...

    def stream_discarded(self, stream_id: int) -> bool: ...

    def session_ended(self, session: WtSession, reason: str, *, local: bool) -> None: ...


@dataclass(eq=False)  # identity equality: sessions are dict keys and set members
class WtSession:
    """Send side of a session plus the dispatch of received events to its handler."""

    conn: SessionConnection
    session_id: int
    remote_address: Address
    is_client: bool
    protocol: str | None = None
    handler: WtSessionHandler | None = None
    closed: bool = False
    _streams: dict[int, _StreamState] = field(default_factory=dict)
    # Events that arrive before the handler exists (client side: a server stream
    # can overtake the CONNECT response) wait here.
    _early: list[Callable[[WtSessionHandler], None]] = field(default_factory=list)
    _closed_event: asyncio.Event = field(default_factory=asyncio.Event)
    # Capsules received on the CONNECT stream (bounded: only CLOSE is read).
    capsules: bytearray = field(default_factory=bytearray)
    # Streams we reset while aioquic held them blocked (over the peer's MAX_STREAMS):
    # their RESET_STREAM waits until the peer's credit covers them (reset_stream).
    _deferred_resets: set[int] = field(default_factory=set)

    # --- sending (called by the protocol code) -------------------------------

    def open_stream(self, is_unidirectional: bool) -> int:
        """Open a WebTransport stream of this session and return its QUIC id."""
        if self.closed:
            raise ConnectionError("WebTransport session is closed")
        stream_id = self.conn.h3.create_webtransport_stream(
            self.session_id, is_unidirectional=is_unidirectional
        )
        self._streams[stream_id] = _StreamState()
        self.conn.register_stream(stream_id, self)
        self.conn.schedule_transmit()
        return stream_id

    def can_open_stream(self, is_unidirectional: bool) -> bool:
        """Whether the peer's MAX_STREAMS lets us open one more stream of this kind now.

        aioquic opens a stream past the peer's credit anyway and holds it "blocked"
        until credit comes; the relay would rather skip a group than queue it there.
        Read from aioquic's QuicConnection: the next local stream id (public) against
        `_remote_max_streams_uni` / `_remote_max_streams_bidi` (private: re-check on an
        aioquic upgrade).
        """
        if self.closed:
            return False
        quic = self.conn.quic
        next_id = quic.get_next_available_stream_id(is_unidirectional)
        if is_unidirectional:
            return next_id // 4 < quic._remote_max_streams_uni
        return next_id // 4 < quic._remote_max_streams_bidi

    def send(self, stream_id: int, data: bytes, end_stream: bool = False) -> None:
        """Queue bytes on a stream. Dropped silently once the stream can no longer
        send (peer STOP_SENDING, our reset, FIN already acknowledged) or the session
        is closed: the relay races these and a late write is not an error."""
        state = self._state(stream_id)
        if self.closed or state is None or state.send_closed:
            return
        try:
            self.conn.quic.send_stream_data(stream_id, data, end_stream)
        except RuntimeError:
            # aioquic: "Cannot send data after the stream was reset" / "after FIN".
            state.send_closed = True
            return
        except ValueError:
            if stream_is_unidirectional(stream_id) and not self.owns_send_side(stream_id):
                raise  # writing to the peer's unidirectional stream is a caller bug
            state.send_closed = True  # stream finished and discarded by aioquic
            return
        if end_stream:
            state.send_closed = True
        self.conn.schedule_transmit()

    def send_datagram(self, data: bytes) -> None:
        if not self.closed:
            self.conn.h3.send_datagram(self.session_id, data)
            self.conn.schedule_transmit()

    def reset_stream(self, stream_id: int, code: int) -> None:
        """Abort our sending side with a WebTransport application code."""
        state = self._state(stream_id)
        if self.closed or state is None:
            return
        state.send_closed = True
        try:
            # aioquic ignores a second reset and a reset after everything was acked.
            self.conn.quic.reset_stream(stream_id, codes.to_http_code(code))
        except ValueError:
            return  # peer's unidirectional stream or discarded: nothing to reset
        self._drop_send_buffer(stream_id)
        stream = self.conn.quic._streams.get(stream_id)
        if stream is not None and stream.is_blocked and stream.sender.reset_pending:
            # aioquic writes RESET_STREAM even for a stream still over the peer's
            # MAX_STREAMS, which the peer must treat as STREAM_LIMIT_ERROR and close
            # the connection. Keep the stream reset in aioquic (no data will go) but
            # hold the frame back until flush_deferred_resets sees it unblocked.
            stream.sender.reset_pending = False
            self._deferred_resets.add(stream_id)
        self.conn.schedule_transmit()

    def flush_deferred_resets(self) -> None:
        """Release the RESET_STREAM of held-back streams the peer's credit now covers.

        Runs right before every network write (WtConnection.transmit): aioquic
        unblocks streams while it reads a MAX_STREAMS frame, and this puts their
        resets back in its queue before that same flush. Private fields, as above.
        """
        if not self._deferred_resets:
            return
        streams = self.conn.quic._streams
        for stream_id in list(self._deferred_resets):
            stream = streams.get(stream_id)
            if stream is None:
                self._deferred_resets.discard(stream_id)  # connection gone or state dropped
            elif not stream.is_blocked:
                stream.sender.reset_pending = True
                self._deferred_resets.discard(stream_id)

    def stop_sending(self, stream_id: int, code: int) -> None:
        """Ask the peer to stop sending on a stream we receive from."""
        if self.closed or self._state(stream_id) is None:
            return
        try:
            self.conn.quic.stop_stream(stream_id, codes.to_http_code(code))
        except ValueError:
            return  # unknown/finished stream: the peer is done sending anyway
        self.conn.schedule_transmit()

    def close(self, code: int = 0, reason: str = "") -> None:
        """End the session: CLOSE_WEBTRANSPORT_SESSION capsule and FIN on the CONNECT
        stream, then the QUIC connection (one session per connection here)."""
        if self.closed:
            return
        reason_bytes = reason.encode("utf-8")[:1024]
        body = (code & 0xFFFFFFFF).to_bytes(4, "big") + reason_bytes
        capsule = (
            encode_uint_var(codes.CLOSE_WEBTRANSPORT_SESSION) + encode_uint_var(len(body)) + body
        )
        try:
            self.conn.h3.send_data(self.session_id, capsule, end_stream=True)
        except Exception:  # the CONNECT stream may already be gone; closing anyway
            log.debug("could not send the close capsule", exc_info=True)
        self.conn.session_ended(self, f"closed locally: {code} {reason}".strip(), local=True)

    # --- back-pressure -------------------------------------------------------

    def buffered_bytes(self, stream_id: int) -> int:
        """Bytes written to the stream and not yet acknowledged by the peer.

        Read from aioquic's QuicStreamSender: `_buffer_stop - _buffer_start` (the
        offset after the last byte written minus the offset of the first byte not
        yet acknowledged), i.e. in flight plus not yet sent. 0 once the stream is
        reset or discarded. Private fields: re-check on an aioquic upgrade.
        """
        stream = self.conn.quic._streams.get(stream_id)
        if stream is None:
            return 0
        sender = stream.sender
        if sender._reset_error_code is not None:
            return 0
        return sender._buffer_stop - sender._buffer_start

    def _drop_send_buffer(self, stream_id: int) -> None:
        """Free the unsent/unacked bytes of a stream we reset.

        aioquic never sends or resends them after a reset but keeps them until the peer
        acknowledges the RESET_STREAM: a viewer that stopped reading would pin every group
        the relay skipped for it until the idle timeout. Private field, as above.
        """
        stream = self.conn.quic._streams.get(stream_id)
        if stream is not None and stream.sender._reset_error_code is not None:
            stream.sender._buffer = bytearray()

    def total_buffered(self) -> int:
        """Sum of buffered_bytes over this session's streams (O(streams known))."""
        return sum(self.buffered_bytes(stream_id) for stream_id in self._streams)

    def owns_send_side(self, stream_id: int) -> bool:
        """Whether we may write: bidi streams, or unidirectional ones we opened."""
        if not stream_is_unidirectional(stream_id):
            return True
        client_initiated = stream_id & 1 == 0
        return client_initiated == self.is_client

    async def wait_closed(self) -> None:
        await self._closed_event.wait()

    # --- dispatch (called by WtConnection) -----------------------------------

    def attach(self, handler: WtSessionHandler) -> None:
        self.handler = handler
        early, self._early = self._early, []
        for call in early:
            self._call(call)

    def deliver_data(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        self._streams.setdefault(stream_id, _StreamState())
        self._call(lambda h: h.on_stream_data(stream_id, data, end_stream))

    def deliver_reset(self, stream_id: int, http_code: int, stop_sending: bool) -> None:
        state = self._streams.setdefault(stream_id, _StreamState())
        if stop_sending:
            state.send_closed = True  # aioquic already reset our sending side
        code = codes.from_http_code(http_code)
        self._call(lambda h: h.on_stream_reset(stream_id, http_code if code is None else code))

    def deliver_datagram(self, data: bytes) -> None:
        def call(h: WtSessionHandler) -> None:
            on_datagram: Callable[[bytes], None] | None = getattr(h, "on_datagram", None)
            if on_datagram is not None:
                on_datagram(data)

        self._call(call)

    def mark_closed(self, reason: str) -> None:
        """Enter the closed state and tell the handler, once."""
        if self.closed:
            return
        self.closed = True
        self._closed_event.set()
        handler = self.handler
        if handler is None:
            self._early.clear()
            return
        try:
            handler.on_closed(reason)
        except Exception:
            log.exception("WebTransport handler on_closed failed")

    def knows_stream(self, stream_id: int) -> bool:
        return stream_id in self._streams

    def forget_stream(self, stream_id: int) -> None:
        self._streams.pop(stream_id, None)

    def _state(self, stream_id: int) -> _StreamState | None:
        """This session's record of a stream; None once aioquic and the adapter
        forgot it (finished long ago: late operations are no-ops). A stream this
        session never saw is a caller bug (it would create a bare QUIC stream)."""
        state = self._streams.get(stream_id)
        if state is None and not self.conn.stream_discarded(stream_id):
            raise ValueError(f"stream {stream_id} is not a stream of this WebTransport session")
        return state

    def _call(self, call: Callable[[WtSessionHandler], None]) -> None:
        if self.closed:
            return
        if self.handler is None:
            self._early.append(call)
            return
        try:
            call(self.handler)
        except Exception:
            # A handler bug ends its own session, never the server.
            log.exception("WebTransport handler failed; closing its session")
            self.close(1, "internal error")
