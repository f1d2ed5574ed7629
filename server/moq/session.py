"""MoqSession: one moq-lite-03 session as a sans-IO state machine (both roles, both sides).

The transport adapter feeds stream bytes in (`receive`, `stream_reset`) and drains
`take_transmit()` (bytes/resets to put on the wire) and `take_events()` (what happened).
Commands (`publish`, `subscribe`, `open_group`, ...) only queue transmits; nothing here
blocks or does I/O. Stream ids come from the adapter's `open_stream(is_unidirectional)`
because HTTP/3 shares the QUIC id space with WebTransport; its optional
`can_open_stream(is_unidirectional)` says whether the peer's stream credit allows one more.

moq-lite is symmetric: whoever opens an announce-interest or subscribe stream is the
subscriber, whoever answers it the publisher, independent of QUIC client/server.

Any malformed input or crossed limit queues one CloseSession and a SessionError event; the
session then ignores all input and its commands do nothing (returning False/None), except
`request_announces` and `subscribe`, which raise SessionClosedError (check `closed`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

from . import paths
from .errors import ErrorCode, ProtocolError
from .events import (
    AnnounceInterestReceived,
    AnnounceReceived,
    AnnouncesEnded,
    Event,
    FrameReceived,
    GoawayReceived,
    GroupCancelled,
    GroupClosed,
    GroupOpened,
    SessionError,
    SubscribeAccepted,
    SubscribeCancelled,
    SubscribeClosed,
    SubscribeDropped,
    SubscribeRequested,
    SubscribeUpdated,
)
from .limits import MoqLimits
from .messages import (
    GROUP_STREAM_TYPE,
    Announce,
    AnnounceInterest,
    Fetch,
    Goaway,
    GroupHeader,
    Probe,
    StreamType,
    Subscribe,
    SubscribeDrop,
    SubscribeOk,
    SubscribeResponseType,
    SubscribeUpdate,
    Version,
    encode,
    encode_frame,
    encode_group_stream_header,
    encode_subscribe_response,
)
from .streams import InboundRequest, Kind, OutboundSubscription, StreamState
from .transmit import (
    CloseSession,
    ResetStream,
    SendData,
    StopSending,
    Transmit,
    is_client_initiated,
    is_unidirectional,
)
from .wire import NeedMore, Reader, encode_varint

# Peer streams we have finished with; late data for them (in flight when we stopped them)
# must be dropped, not parsed as a new stream. Bounded: the oldest ids are forgotten.
_FINISHED_MEMORY = 8192


class SessionClosedError(RuntimeError):
    """A command that must return an id was called on a closed session."""


class MoqSession:
    def __init__(
        self,
        *,
        is_client: bool,
        open_stream: Callable[[bool], int],
        can_open_stream: Callable[[bool], bool] | None = None,
        limits: MoqLimits | None = None,
        version: Version = Version.LITE_03,
    ) -> None:
        """``can_open_stream`` (None: always) gates group streams only: a group is
        worth dropping, a request stream is not (it waits in the transport instead)."""
        self.is_client = is_client
        self.limits = limits or MoqLimits()
        self.version = version
        self.closed = False
        self.bytes_received = 0
        self.bytes_sent = 0
        self._open_stream = open_stream
        self._can_open_stream = can_open_stream
        self._transmit: list[Transmit] = []
        self._events: list[Event] = []
        self._streams: dict[int, StreamState] = {}
        self._finished: OrderedDict[int, None] = OrderedDict()
        self._incoming = 0  # open peer-initiated streams
        self._buffered = 0  # unparsed bytes over all streams
        self._published: dict[str, int] = {}  # path -> hop count
        self._interests: dict[int, str] = {}  # peer interest stream -> prefix
        self._requests: dict[int, InboundRequest] = {}
        self._out_groups: dict[int, int] = {}  # our group stream -> request id
        self._subscriptions: dict[int, OutboundSubscription] = {}
        self._next_subscription_id = 0

    # ----------------------------------------------------------------- adapter side

    def take_transmit(self) -> list[Transmit]:
        out, self._transmit = self._transmit, []
        return out

    def take_events(self) -> list[Event]:
        out, self._events = self._events, []
        return out

    def receive(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        if self.closed:
            return
        try:
            self._receive(stream_id, data, end_stream)
        except ProtocolError as exc:
            self._fail(exc.code, exc.reason)

    def stream_reset(self, stream_id: int, error_code: int) -> None:
        """The peer reset its side of a stream or asked us to stop sending on it."""
        if self.closed:
            return
        request_id = self._out_groups.pop(stream_id, None)
        if request_id is not None:
            request = self._requests.get(request_id)
            if request is not None:
                request.groups.discard(stream_id)
            self._send(ResetStream(stream_id, ErrorCode.CANCEL))
            self._events.append(GroupCancelled(request_id, stream_id, error_code))
            return
        state = self._streams.get(stream_id)
        if state is not None:
            self._end_stream(state, error_code)

    def close(self, error_code: int = ErrorCode.CANCEL, reason: str = "") -> None:
        """Close the session from our side (no SessionError event: we asked)."""
        if not self.closed:
            self._send(CloseSession(error_code, reason))
            self._shutdown()

    # -------------------------------------------------------------- publisher side

    def publish(self, path: str, hop_count: int = 0) -> None:
        """Announce `path` to every current and future announce interest that covers it."""
        path = paths.normalize(path)
        if self.closed or path in self._published:
            return
        self._published[path] = hop_count
        for stream_id, prefix in self._interests.items():
            self._announce(stream_id, prefix, path, True, hop_count)

    def unpublish(self, path: str) -> None:
        path = paths.normalize(path)
        if self.closed or path not in self._published:
            return
        hop_count = self._published.pop(path)
        for stream_id, prefix in self._interests.items():
            self._announce(stream_id, prefix, path, False, hop_count)

    @property
    def published(self) -> frozenset[str]:
        return frozenset(self._published)

    def accept_subscribe(self, request_id: int, ok: SubscribeOk | None = None) -> bool:
        """Send SUBSCRIBE_OK (by default echoing the request); False if no such request."""
        request = self._requests.get(request_id)
        if self.closed or request is None or request.accepted:
            return False
        if ok is None:
            ok = SubscribeOk(request.priority, request.ordered, request.max_latency_ms)
        request.accepted = True
        self._send(SendData(request.stream_id, encode_subscribe_response(ok, self.version)))
        return True

    def reject_subscribe(self, request_id: int, error_code: int = ErrorCode.NOT_FOUND) -> bool:
        """Refuse by resetting the subscribe stream, as @moq/lite's publisher does."""
        request = self._requests.get(request_id)
        if self.closed or request is None:
            return False
        self._drop_request(request_id, error_code, reset=True)
        return True

    def end_subscription(self, request_id: int) -> bool:
        """The track is over: FIN the subscribe stream. Open groups stay writable."""
        request = self._requests.pop(request_id, None)
        if self.closed or request is None:
            return False
        self._send(SendData(request.stream_id, b"", end_stream=True))
        self._send(StopSending(request.stream_id, ErrorCode.CANCEL))
        self._forget(request.stream_id)
        return True

    def drop_groups(self, request_id: int, start: int, end: int, error_code: int) -> bool:
        """Tell the subscriber groups start..end will not come (SUBSCRIBE_DROP)."""
        request = self._requests.get(request_id)
        if self.closed or request is None or not request.accepted:
            return False
        drop = SubscribeDrop(start, end, error_code)
        self._send(SendData(request.stream_id, encode_subscribe_response(drop, self.version)))
        return True

    def request(self, request_id: int) -> InboundRequest | None:
        return self._requests.get(request_id)

    def open_group(self, request_id: int, sequence: int) -> int | None:
        """Open the uni stream of one group; None if the request (or session) is gone, or
        if the peer's stream credit (QUIC MAX_STREAMS) is used up: then nothing is opened
        and the caller drops the group (a stream queued past the credit would only
        deliver it late, and resetting it there is a violation the peer closes on)."""
        request = self._requests.get(request_id)
        if self.closed or request is None or not request.accepted:
            return None
        if self._can_open_stream is not None and not self._can_open_stream(True):
            return None
        stream_id = self._open_stream(True)
        header = GroupHeader(request_id, sequence)
        self._send(SendData(stream_id, encode_group_stream_header(header, self.version)))
        self._out_groups[stream_id] = request_id
        request.groups.add(stream_id)
        return stream_id

    def write_frame(self, stream_id: int, payload: bytes) -> bool:
        """False when the group stream is gone (cancelled by the peer or closed)."""
        if self.closed or stream_id not in self._out_groups:
            return False
        self._send(SendData(stream_id, encode_frame(payload)))
        return True

    def finish_group(self, stream_id: int) -> bool:
        if not self._release_group(stream_id):
            return False
        self._send(SendData(stream_id, b"", end_stream=True))
        return True

    def abort_finished_group(self, stream_id: int, error_code: int = ErrorCode.CANCEL) -> bool:
        """Reset a group stream we already finished (FIN) whose bytes are not all
        delivered: a group that went stale in the send queue. QUIC allows RESET_STREAM
        after FIN until everything is acknowledged; the adapter makes it a no-op after."""
        if self.closed or stream_id in self._out_groups or not self._is_local(stream_id):
            return False
        self._send(ResetStream(stream_id, error_code))
        return True

    def abort_group(self, stream_id: int, error_code: int = ErrorCode.CANCEL) -> bool:
        if not self._release_group(stream_id):
            return False
        self._send(ResetStream(stream_id, error_code))
        return True

    def send_probe(self, stream_id: int, bitrate: int, rtt_ms: int | None = None) -> bool:
        """Answer a peer's probe stream with our estimate of the bitrate towards it."""
        state = self._streams.get(stream_id)
        if self.closed or state is None or state.kind is not Kind.PROBE_IN:
            return False
        self._send(SendData(stream_id, encode(Probe(bitrate, rtt_ms), self.version)))
        return True

    # ------------------------------------------------------------- subscriber side

    def request_announces(self, prefix: str = "") -> int:
        """Open an announce interest; AnnounceReceived events carry the returned handle."""
        if self.closed:
            raise SessionClosedError("session closed")
        prefix = paths.normalize(prefix)
        stream_id = self._open_stream(False)
        message = encode_varint(StreamType.ANNOUNCE) + encode(
            AnnounceInterest(prefix), self.version
        )
        self._send(SendData(stream_id, message))
        self._streams[stream_id] = StreamState(stream_id, Kind.ANNOUNCE_OUT, prefix=prefix)
        return stream_id

    def cancel_announces(self, handle: int) -> bool:
        state = self._streams.get(handle)
        if self.closed or state is None or state.kind is not Kind.ANNOUNCE_OUT:
            return False
        self._close_local(state)
        return True

    def subscribe(
        self,
        broadcast: str,
        track: str,
        *,
        priority: int = 0,
        ordered: bool = False,
        max_latency_ms: int = 0,
        start_group: int | None = None,
        end_group: int | None = None,
    ) -> int:
        """Open a subscription; its events carry the returned subscription id."""
        if self.closed:
            raise SessionClosedError("session closed")
        subscription_id = self._next_subscription_id
        self._next_subscription_id += 1
        broadcast = paths.normalize(broadcast)
        message = Subscribe(
            subscription_id,
            broadcast,
            track,
            priority,
            ordered,
            max_latency_ms,
            start_group,
            end_group,
        )
        stream_id = self._open_stream(False)
        data = encode_varint(StreamType.SUBSCRIBE) + encode(message, self.version)
        self._send(SendData(stream_id, data))
        self._streams[stream_id] = StreamState(
            stream_id, Kind.SUBSCRIBE_OUT, ref_id=subscription_id
        )
        self._subscriptions[subscription_id] = OutboundSubscription(stream_id, broadcast, track)
        return subscription_id

    def update_subscription(self, subscription_id: int, update: SubscribeUpdate) -> bool:
        subscription = self._subscriptions.get(subscription_id)
        if self.closed or subscription is None:
            return False
        self._send(SendData(subscription.stream_id, encode(update, self.version)))
        return True

    def unsubscribe(self, subscription_id: int) -> bool:
        """Stop a subscription and every group stream still arriving for it."""
        subscription = self._subscriptions.pop(subscription_id, None)
        if self.closed or subscription is None:
            return False
        state = self._streams.get(subscription.stream_id)
        if state is not None:
            self._close_local(state)
        for group in [s for s in self._streams.values() if s.kind is Kind.GROUP_IN]:
            if group.ref_id == subscription_id:
                self._send(StopSending(group.stream_id, ErrorCode.CANCEL))
                self._forget(group.stream_id)
        return True

    # ------------------------------------------------------------------- internals

    def _send(self, transmit: Transmit) -> None:
        if isinstance(transmit, SendData):
            self.bytes_sent += len(transmit.data)
        self._transmit.append(transmit)

    def _fail(self, code: ErrorCode, reason: str) -> None:
        self._send(CloseSession(code, reason))
        self._events.append(SessionError(code, reason))
        self._shutdown()

    def _shutdown(self) -> None:
        self.closed = True
        self._streams.clear()
        self._requests.clear()
        self._subscriptions.clear()
        self._out_groups.clear()
        self._interests.clear()
        self._buffered = 0

    def _is_local(self, stream_id: int) -> bool:
        return is_client_initiated(stream_id) == self.is_client

    def _receive(self, stream_id: int, data: bytes, end_stream: bool) -> None:
        self.bytes_received += len(data)
        state = self._streams.get(stream_id)
        if state is None:
            if self._is_local(stream_id):
                if is_unidirectional(stream_id):
                    raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "data on our uni stream")
                return  # a bidi stream of ours we already closed: late bytes
            if stream_id in self._finished:
                return
            if self._incoming >= self.limits.max_incoming_streams:
                raise ProtocolError(ErrorCode.LIMIT_EXCEEDED, "too many concurrent streams")
            kind = Kind.UNI_NEW if is_unidirectional(stream_id) else Kind.BIDI_NEW
            state = StreamState(stream_id, kind)
            self._streams[stream_id] = state
            self._incoming += 1
        if state.fin_received:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "data after FIN")
        if state.kind is Kind.DISCARD or state.kind is Kind.PROBE_IN:
            data = b""  # nothing there is used; do not let it pile up
        state.buffer += data
        self._buffered += len(data)
        if self._buffered > self.limits.max_buffered_bytes:
            raise ProtocolError(ErrorCode.LIMIT_EXCEEDED, "too many buffered bytes")
        state.fin_received = end_stream
        self._parse(state)

    def _parse(self, state: StreamState) -> None:
        # One Reader for all complete items, one `del` at the end: no quadratic copying when
        # a chunk holds many small frames. `consumed` only moves past whole items.
        reader = Reader(state.buffer, complete=False)
        consumed = 0
        try:
            while self._streams.get(state.stream_id) is state and reader.remaining:
                self._step(state, reader)
                consumed = reader.pos
        except NeedMore:
            pass
        finally:
            reader.release()
        if self._streams.get(state.stream_id) is state:  # else _forget accounted for it
            del state.buffer[:consumed]
            self._buffered -= consumed
        if self._streams.get(state.stream_id) is state and state.fin_received:
            if state.buffer:
                raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "stream ended mid-message")
            self._end_stream(state, None)

    def _message(self, reader: Reader) -> Reader:
        return reader.message(self.limits.max_message_size)

    def _step(self, state: StreamState, r: Reader) -> None:
        """Parse one item from the stream buffer and act on it (atomic: NeedMore first)."""
        kind = state.kind
        if kind is Kind.BIDI_NEW:
            state.kind = self._bidi_kind(r.varint())
        elif kind is Kind.ANNOUNCE_IN_WAIT:
            body = self._message(r)
            interest = AnnounceInterest.decode(body, self.version)
            body.expect_end()
            self._on_interest(state, paths.normalize(interest.prefix))
        elif kind is Kind.SUBSCRIBE_IN_WAIT:
            body = self._message(r)
            subscribe = Subscribe.decode(body, self.version)
            body.expect_end()
            self._on_subscribe(state, subscribe)
        elif kind is Kind.SUBSCRIBE_IN:
            body = self._message(r)
            update = SubscribeUpdate.decode(body, self.version)
            body.expect_end()
            self._events.append(
                SubscribeUpdated(
                    state.ref_id,
                    update.priority,
                    update.ordered,
                    update.max_latency_ms,
                    update.start_group,
                    update.end_group,
                )
            )
        elif kind is Kind.FETCH_IN:
            body = self._message(r)
            Fetch.decode(body, self.version)
            body.expect_end()
            # We keep no history to fetch from; refuse without hurting the session.
            self._send(ResetStream(state.stream_id, ErrorCode.UNSUPPORTED))
            self._send(StopSending(state.stream_id, ErrorCode.UNSUPPORTED))
            self._forget(state.stream_id)
        elif kind is Kind.GOAWAY_IN:
            body = self._message(r)
            goaway = Goaway.decode(body, self.version)
            body.expect_end()
            self._events.append(GoawayReceived(goaway.uri))
            state.kind = Kind.DISCARD
        elif kind is Kind.ANNOUNCE_IN:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "data after announce interest")
        elif kind is Kind.ANNOUNCE_OUT:
            body = self._message(r)
            announce = Announce.decode(body, self.version)
            body.expect_end()
            path = paths.join(state.prefix, paths.normalize(announce.suffix))
            self._events.append(
                AnnounceReceived(state.stream_id, path, announce.active, announce.hop_count)
            )
        elif kind is Kind.SUBSCRIBE_OUT:
            self._on_subscribe_response(state, r)
        elif kind is Kind.UNI_NEW:
            self._on_group_header(state, r)
        elif kind is Kind.GROUP_IN:
            size = r.varint()
            if size > self.limits.max_frame_size:
                raise ProtocolError(ErrorCode.LIMIT_EXCEEDED, f"frame of {size} bytes")
            payload = r.raw(size)
            self._events.append(
                FrameReceived(state.ref_id, state.sequence, state.stream_id, payload)
            )
        else:  # DISCARD / PROBE_IN buffers stay empty; nothing to parse
            r.raw(r.remaining)

    def _bidi_kind(self, stream_type: int) -> Kind:
        kinds: dict[int, Kind] = {
            StreamType.ANNOUNCE: Kind.ANNOUNCE_IN_WAIT,
            StreamType.SUBSCRIBE: Kind.SUBSCRIBE_IN_WAIT,
            StreamType.FETCH: Kind.FETCH_IN,
            StreamType.PROBE: Kind.PROBE_IN,
            StreamType.GOAWAY: Kind.GOAWAY_IN,
        }
        kind = kinds.get(stream_type)
        if kind is None:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, f"bidi stream type {stream_type}")
        return kind

    def _on_interest(self, state: StreamState, prefix: str) -> None:
        if len(self._interests) >= self.limits.max_announce_interests:
            raise ProtocolError(ErrorCode.LIMIT_EXCEEDED, "too many announce interests")
        state.kind = Kind.ANNOUNCE_IN
        state.prefix = prefix
        self._interests[state.stream_id] = prefix
        self._events.append(AnnounceInterestReceived(state.stream_id, prefix))
        for path, hop_count in self._published.items():
            self._announce(state.stream_id, prefix, path, True, hop_count)

    def _announce(self, stream_id: int, prefix: str, path: str, active: bool, hops: int) -> None:
        suffix = paths.strip_prefix(prefix, path)
        if suffix is not None:
            message = Announce(active, suffix, hops)
            self._send(SendData(stream_id, encode(message, self.version)))

    def _on_subscribe(self, state: StreamState, msg: Subscribe) -> None:
        if msg.id in self._requests:
            raise ProtocolError(ErrorCode.DUPLICATE, f"subscription id {msg.id} in use")
        if len(self._requests) >= self.limits.max_subscriptions:
            raise ProtocolError(ErrorCode.LIMIT_EXCEEDED, "too many subscriptions")
        state.kind = Kind.SUBSCRIBE_IN
        state.ref_id = msg.id
        broadcast = paths.normalize(msg.broadcast)
        self._requests[msg.id] = InboundRequest(
            state.stream_id, broadcast, msg.track, msg.priority, msg.ordered, msg.max_latency_ms
        )
        self._events.append(
            SubscribeRequested(
                msg.id,
                broadcast,
                msg.track,
                msg.priority,
                msg.ordered,
                msg.max_latency_ms,
                msg.start_group,
                msg.end_group,
            )
        )

    def _on_subscribe_response(self, state: StreamState, r: Reader) -> None:
        response_type = r.varint()
        body = self._message(r)
        subscription = self._subscriptions.get(state.ref_id)
        if response_type == SubscribeResponseType.OK:
            ok = SubscribeOk.decode(body, self.version)
            body.expect_end()
            if subscription is None or subscription.accepted:
                raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "duplicate SUBSCRIBE_OK")
            subscription.accepted = True
            self._events.append(
                SubscribeAccepted(
                    state.ref_id,
                    ok.priority,
                    ok.ordered,
                    ok.max_latency_ms,
                    ok.start_group,
                    ok.end_group,
                )
            )
        elif response_type == SubscribeResponseType.DROP:
            drop = SubscribeDrop.decode(body, self.version)
            body.expect_end()
            self._events.append(SubscribeDropped(state.ref_id, drop.start, drop.end, drop.error))
        else:
            raise ProtocolError(
                ErrorCode.PROTOCOL_VIOLATION, f"subscribe response type {response_type}"
            )

    def _on_group_header(self, state: StreamState, r: Reader) -> None:
        stream_type = r.u8()
        if stream_type != GROUP_STREAM_TYPE:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, f"uni stream type {stream_type}")
        body = self._message(r)
        header = GroupHeader.decode(body, self.version)
        body.expect_end()
        if header.subscribe_id not in self._subscriptions:
            if header.subscribe_id >= self._next_subscription_id:
                raise ProtocolError(
                    ErrorCode.PROTOCOL_VIOLATION, f"group for unknown id {header.subscribe_id}"
                )
            # A subscription we already ended: its groups may still be in flight.
            self._send(StopSending(state.stream_id, ErrorCode.CANCEL))
            self._forget(state.stream_id)
            return
        state.kind = Kind.GROUP_IN
        state.ref_id = header.subscribe_id
        state.sequence = header.sequence
        self._events.append(GroupOpened(header.subscribe_id, header.sequence, state.stream_id))

    def _end_stream(self, state: StreamState, error_code: int | None) -> None:
        """The peer finished (error_code None) or reset a stream we track."""
        kind = state.kind
        stream_id = state.stream_id
        self._forget(stream_id)
        reset = error_code is not None
        if kind is Kind.ANNOUNCE_IN:
            del self._interests[stream_id]
            self._reply_close(stream_id, reset)
        elif kind is Kind.SUBSCRIBE_IN:
            if state.ref_id in self._requests:
                self._drop_request(state.ref_id, ErrorCode.CANCEL, reset=reset)
                self._events.append(SubscribeCancelled(state.ref_id, error_code))
        elif kind is Kind.PROBE_IN or kind is Kind.DISCARD or kind is Kind.BIDI_NEW:
            if not is_unidirectional(stream_id):
                self._reply_close(stream_id, reset)
        elif kind is Kind.ANNOUNCE_OUT:
            self._events.append(AnnouncesEnded(stream_id, error_code))
            self._reply_close(stream_id, reset)
        elif kind is Kind.SUBSCRIBE_OUT:
            subscription = self._subscriptions.pop(state.ref_id, None)
            if subscription is not None:
                self._events.append(
                    SubscribeClosed(state.ref_id, error_code, subscription.accepted)
                )
                self._reply_close(stream_id, reset)
        elif kind is Kind.GROUP_IN:
            self._events.append(
                GroupClosed(state.ref_id, state.sequence, stream_id, not reset, error_code)
            )
        elif not reset:
            # The peer closed a request stream before sending the request.
            self._reply_close(stream_id, reset)

    def _reply_close(self, stream_id: int, reset: bool) -> None:
        if reset:
            self._send(ResetStream(stream_id, ErrorCode.CANCEL))
        else:
            self._send(SendData(stream_id, b"", end_stream=True))

    def _close_local(self, state: StreamState) -> None:
        """We are done with one of our own bidi streams (FIN + STOP_SENDING)."""
        self._send(SendData(state.stream_id, b"", end_stream=True))
        self._send(StopSending(state.stream_id, ErrorCode.CANCEL))
        self._forget(state.stream_id)

    def _drop_request(self, request_id: int, error_code: int, *, reset: bool) -> None:
        request = self._requests.pop(request_id)
        for group in request.groups:
            self._out_groups.pop(group, None)
            self._send(ResetStream(group, ErrorCode.CANCEL))
        if reset:
            self._send(ResetStream(request.stream_id, error_code))
            self._send(StopSending(request.stream_id, error_code))
        else:
            self._send(SendData(request.stream_id, b"", end_stream=True))
        self._forget(request.stream_id)

    def _release_group(self, stream_id: int) -> bool:
        if self.closed:
            return False
        request_id = self._out_groups.pop(stream_id, None)
        if request_id is None:
            return False
        request = self._requests.get(request_id)
        if request is not None:
            request.groups.discard(stream_id)
        return True

    def _forget(self, stream_id: int) -> None:
        """Stop tracking a stream; remember peer ones so late bytes are dropped."""
        state = self._streams.pop(stream_id, None)
        if state is None:
            return
        self._buffered -= len(state.buffer)
        state.buffer = bytearray()  # not clear(): a Reader may still view the old one
        if not self._is_local(stream_id):
            self._incoming -= 1
            self._finished[stream_id] = None
            if len(self._finished) > _FINISHED_MEMORY:
                self._finished.popitem(last=False)
