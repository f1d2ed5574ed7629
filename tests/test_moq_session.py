"""MoqSession end to end over the in-memory pipe, limits, and fuzzing of `receive`."""

from __future__ import annotations

from collections.abc import Iterable
from itertools import pairwise
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.moq import events as ev
from server.moq import messages as m
from server.moq.errors import ErrorCode
from server.moq.limits import MoqLimits
from server.moq.session import MoqSession
from server.moq.transmit import CloseSession, ResetStream, SendData, StopSending
from server.moq.wire import encode_varint
from tests.moq_pipe import Pipe, StreamIds


def split(data: bytes, cuts: Iterable[int]) -> list[bytes]:
    """`data` cut at the given offsets (empty pieces included: receive must cope)."""
    bounds = [0, *sorted(set(cuts)), len(data)]
    return [data[a:b] for a, b in pairwise(bounds)]


def of(events: list[Any], kind: type) -> list[Any]:
    return [e for e in events if isinstance(e, kind)]


def subscribed_pipe() -> tuple[Pipe, int, int]:
    """A pipe where the client subscribed to the server's `game`/`video` and was accepted."""
    pipe = Pipe()
    pipe.server.publish("game")
    sub = pipe.client.subscribe("game", "video", priority=2, max_latency_ms=500)
    pipe.flush()
    (request,) = of(pipe.server.take_events(), ev.SubscribeRequested)
    assert (request.broadcast, request.track, request.priority) == ("game", "video", 2)
    assert request.max_latency_ms == 500
    assert pipe.server.accept_subscribe(request.request_id)
    pipe.flush()
    (accepted,) = of(pipe.client.take_events(), ev.SubscribeAccepted)
    assert accepted.subscription_id == sub and accepted.priority == 2
    return pipe, sub, request.request_id


def test_stream_numbering_follows_quic() -> None:
    client, server = StreamIds(True), StreamIds(False)
    assert [client.open(False) for _ in range(3)] == [0, 4, 8]
    assert [server.open(False), server.open(True), client.open(True)] == [1, 3, 2]


def test_announces_follow_publish_and_prefix() -> None:
    pipe = Pipe()
    pipe.server.publish("game")
    pipe.server.publish("gamebar")  # "game" is not a segment prefix of it
    handle = pipe.client.request_announces("game/")
    pipe.flush()
    (interest,) = of(pipe.server.take_events(), ev.AnnounceInterestReceived)
    assert interest.prefix == "game"
    pipe.server.publish("game/input/abc")
    pipe.server.unpublish("game")
    pipe.server.unpublish("game")  # idempotent
    pipe.flush()
    got = [(e.handle, e.path, e.active) for e in of(pipe.client.take_events(), ev.AnnounceReceived)]
    assert got == [
        (handle, "game", True),
        (handle, "game/input/abc", True),
        (handle, "game", False),
    ]
    pipe.client.cancel_announces(handle)
    pipe.flush()
    pipe.server.publish("game/x")
    pipe.flush()
    assert pipe.client.take_events() == []
    assert pipe.closes == {}


def test_group_frames_arrive_whole_and_in_order() -> None:
    pipe, sub, request = subscribed_pipe()
    stream = pipe.server.open_group(request, 4)
    assert stream is not None and stream % 4 == 3  # server uni
    for payload in (b"key", b"", b"x" * 70000):
        assert pipe.server.write_frame(stream, payload)
    assert pipe.server.finish_group(stream)
    assert not pipe.server.write_frame(stream, b"late")
    pipe.flush()
    events = pipe.client.take_events()
    assert events[0] == ev.GroupOpened(sub, 4, stream)
    assert [e.payload for e in of(events, ev.FrameReceived)] == [b"key", b"", b"x" * 70000]
    assert events[-1] == ev.GroupClosed(sub, 4, stream, True, None)


def test_group_reset_reports_incomplete() -> None:
    pipe, sub, request = subscribed_pipe()
    stream = pipe.server.open_group(request, 0)
    assert stream is not None
    pipe.server.write_frame(stream, b"a")
    pipe.server.abort_group(stream, ErrorCode.SKIPPED)
    pipe.flush()
    assert pipe.client.take_events()[-1] == ev.GroupClosed(sub, 0, stream, False, 7)


def test_reject_subscribe_is_a_stream_reset_not_a_session_error() -> None:
    pipe = Pipe()
    sub = pipe.client.subscribe("missing", "video")
    pipe.flush()
    (request,) = of(pipe.server.take_events(), ev.SubscribeRequested)
    pipe.server.reject_subscribe(request.request_id, ErrorCode.NOT_FOUND)
    pipe.flush()
    assert pipe.client.take_events() == [ev.SubscribeClosed(sub, ErrorCode.NOT_FOUND, False)]
    assert pipe.closes == {} and not pipe.client.closed and not pipe.server.closed


def test_end_subscription_closes_the_subscriber_side() -> None:
    pipe, sub, request = subscribed_pipe()
    pipe.server.end_subscription(request)
    pipe.flush()
    assert pipe.client.take_events() == [ev.SubscribeClosed(sub, None, True)]
    assert pipe.server.take_events() == []


def test_unsubscribe_cancels_request_and_late_groups_are_stopped() -> None:
    pipe, sub, request = subscribed_pipe()
    stream = pipe.server.open_group(request, 1)
    assert stream is not None
    pipe.flush()
    pipe.client.take_events()
    pipe.client.unsubscribe(sub)
    pipe.flush()
    assert ev.SubscribeCancelled(request, None) in pipe.server.take_events()
    assert not pipe.server.write_frame(stream, b"x")
    # A group that was already in flight for the ended subscription is stopped, not fatal.
    late = 3 + 4 * 10
    header = m.encode_group_stream_header(m.GroupHeader(sub, 2))
    pipe.client.receive(late, header + m.encode_frame(b"zz"), False)
    assert pipe.client.take_transmit() == [StopSending(late, ErrorCode.CANCEL)]
    assert pipe.client.take_events() == [] and not pipe.client.closed


def test_group_for_never_used_subscription_id_is_fatal() -> None:
    pipe = Pipe()
    header = m.encode_group_stream_header(m.GroupHeader(5, 0))
    pipe.client.receive(3, header, False)
    (close,) = pipe.client.take_transmit()
    assert isinstance(close, CloseSession) and close.error_code == ErrorCode.PROTOCOL_VIOLATION
    assert isinstance(pipe.client.take_events()[0], ev.SessionError)
    pipe.client.receive(7, b"\x00", False)  # ignored from now on
    assert pipe.client.take_transmit() == [] and pipe.client.take_events() == []


def test_peer_reset_of_subscribe_stream() -> None:
    pipe, sub, request = subscribed_pipe()
    stream = pipe.server.open_group(request, 0)
    pipe.server.take_transmit()
    pipe.server.stream_reset(0, 9)  # the client's subscribe bidi (client bidi 0)
    assert ev.SubscribeCancelled(request, 9) in pipe.server.take_events()
    assert ResetStream(stream or -1, ErrorCode.CANCEL) in pipe.server.take_transmit()
    pipe.client.stream_reset(0, 9)
    assert pipe.client.take_events() == [ev.SubscribeClosed(sub, 9, True)]


def test_fetch_refused_probe_held_goaway_reported() -> None:
    server = MoqSession(is_client=False, open_stream=StreamIds(False).open)
    fetch = encode_varint(m.StreamType.FETCH) + m.encode(m.Fetch("game", "video", 0, 3))
    server.receive(0, fetch, False)
    assert server.take_transmit() == [
        ResetStream(0, ErrorCode.UNSUPPORTED),
        StopSending(0, ErrorCode.UNSUPPORTED),
    ]
    server.receive(4, encode_varint(m.StreamType.PROBE), False)
    assert server.take_transmit() == []
    assert server.send_probe(4, 5_000_000)
    assert server.take_transmit() == [SendData(4, m.encode(m.Probe(5_000_000)))]
    server.receive(4, b"", True)
    assert server.take_transmit() == [SendData(4, b"", True)]
    server.receive(8, encode_varint(m.StreamType.GOAWAY) + m.encode(m.Goaway("x")), True)
    assert server.take_events() == [ev.GoawayReceived("x")]
    assert not server.closed


@pytest.mark.parametrize(
    ("limits", "data"),
    [
        (MoqLimits(max_message_size=8), b"\x02" + m.encode(m.Subscribe(0, "game", "video"))),
        (MoqLimits(max_frame_size=4), None),
    ],
)
def test_size_limits_close_the_session(limits: MoqLimits, data: bytes | None) -> None:
    if data is None:  # a frame too large for the subscriber
        pipe = Pipe(client_limits=limits)
        pipe.server.publish("game")
        sub = pipe.client.subscribe("game", "video")
        pipe.flush()
        (req,) = of(pipe.server.take_events(), ev.SubscribeRequested)
        pipe.server.accept_subscribe(req.request_id)
        stream = pipe.server.open_group(req.request_id, 0)
        assert stream is not None and sub == 0
        pipe.server.write_frame(stream, b"12345")
        pipe.flush()
        assert pipe.closes["client"].error_code == ErrorCode.LIMIT_EXCEEDED
        return
    server = MoqSession(is_client=False, open_stream=StreamIds(False).open, limits=limits)
    server.receive(0, data, False)
    (close,) = server.take_transmit()
    assert isinstance(close, CloseSession) and close.error_code == ErrorCode.LIMIT_EXCEEDED


def test_subscribe_storm_is_bounded() -> None:
    pipe = Pipe(server_limits=MoqLimits(max_subscriptions=8))
    for i in range(20):
        pipe.client.subscribe("game", f"t{i}")
    pipe.flush()
    assert len(of(pipe.server.take_events(), ev.SubscribeRequested)) == 8
    assert pipe.closes["server"].error_code == ErrorCode.LIMIT_EXCEEDED
    assert pipe.server.closed


def test_interest_and_stream_limits() -> None:
    pipe = Pipe(server_limits=MoqLimits(max_announce_interests=2))
    for _ in range(3):
        pipe.client.request_announces("")
    pipe.flush()
    assert pipe.closes["server"].error_code == ErrorCode.LIMIT_EXCEEDED
    server = MoqSession(
        is_client=False,
        open_stream=StreamIds(False).open,
        limits=MoqLimits(max_incoming_streams=3),
    )
    for i in range(4):
        server.receive(2 + 4 * i, b"\x00", False)  # half-read group headers stay open
    assert isinstance(server.take_transmit()[-1], CloseSession)


def test_duplicate_subscription_id_is_fatal() -> None:
    server = MoqSession(is_client=False, open_stream=StreamIds(False).open)
    sub = b"\x02" + m.encode(m.Subscribe(1, "game", "video"))
    server.receive(0, sub, False)
    server.receive(4, sub, False)
    assert server.closed
    assert server.take_transmit()[-1] == CloseSession(
        ErrorCode.DUPLICATE, "subscription id 1 in use"
    )


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_random_chunking_delivers_the_same_events(data: st.DataObject) -> None:
    """Every transmit is cut at random byte boundaries; frames still arrive whole, once."""
    pipe, sub, request = subscribed_pipe()
    payloads = data.draw(st.lists(st.binary(max_size=300), min_size=1, max_size=6))
    stream = pipe.server.open_group(request, 9)
    assert stream is not None
    for payload in payloads:
        pipe.server.write_frame(stream, payload)
    pipe.server.finish_group(stream)
    for transmit in pipe.server.take_transmit():
        assert isinstance(transmit, SendData)
        cuts = sorted(data.draw(st.sets(st.integers(0, len(transmit.data)), max_size=5)))
        pieces = split(transmit.data, cuts)
        for i, piece in enumerate(pieces):
            last = i == len(pieces) - 1
            pipe.client.receive(transmit.stream_id, piece, transmit.end_stream and last)
    events = pipe.client.take_events()
    assert [e.payload for e in of(events, ev.FrameReceived)] == payloads
    assert events[-1] == ev.GroupClosed(sub, 9, stream, True, None)


PREFIXES = st.sampled_from(
    [
        b"",
        b"\x01",  # announce interest
        b"\x02",  # subscribe
        b"\x02" + m.encode(m.Subscribe(0, "game", "video")),
        b"\x03",
        b"\x04",
        b"\x05",
        b"\x01" + m.encode(m.AnnounceInterest("")),
    ]
)


@settings(max_examples=300, deadline=None)
@given(
    is_client=st.booleans(),
    uni=st.booleans(),
    prefix=PREFIXES,
    tail=st.binary(max_size=80),
    cuts=st.lists(st.integers(0, 100), max_size=4),
    fin=st.booleans(),
    reset=st.booleans(),
)
def test_receive_random_bytes_never_raises(
    is_client: bool,
    uni: bool,
    prefix: bytes,
    tail: bytes,
    cuts: list[int],
    fin: bool,
    reset: bool,
) -> None:
    session = MoqSession(
        is_client=is_client, open_stream=StreamIds(is_client).open, limits=MoqLimits(8, 64)
    )
    session.subscribe("game", "video")  # so a group stream for id 0 is valid
    session.take_transmit()
    peer_bit = 0 if is_client else 1  # the peer's streams have the other role's bit 0
    stream_id = (1 - peer_bit) | (2 if uni else 0)
    wire = (b"\x00" + m.encode(m.GroupHeader(0, 1)) if uni else prefix) + tail
    pieces = split(wire, [c for c in cuts if c < len(wire)])
    for i, piece in enumerate(pieces):
        session.receive(stream_id, piece, fin and i == len(pieces) - 1)
    if reset:
        session.stream_reset(stream_id, 1)
    session.receive(stream_id + 4, tail, fin)
    transmits = session.take_transmit()
    closes = [t for t in transmits if isinstance(t, CloseSession)]
    assert len(closes) <= 1
    assert session.closed == bool(closes)
    for close in closes:
        assert close.error_code in set(ErrorCode)
    session.take_events()


OPS = st.lists(
    st.tuples(
        st.integers(0, 15),  # which stream: low bits = QUIC type, high bits = index
        st.binary(max_size=24),
        st.booleans(),  # fin
        st.booleans(),  # reset instead of data
    ),
    max_size=25,
)


@settings(max_examples=300, deadline=None)
@given(is_client=st.booleans(), ops=OPS)
def test_random_operations_on_many_streams_never_raise(
    is_client: bool, ops: list[tuple[int, bytes, bool, bool]]
) -> None:
    """Interleaved bytes, FINs and resets on peer and own streams of both directions."""
    session = MoqSession(
        is_client=is_client, open_stream=StreamIds(is_client).open, limits=MoqLimits(16, 32)
    )
    session.request_announces("")
    session.subscribe("game", "video")
    session.publish("game")
    for choice, data, fin, reset in ops:
        stream_id = (choice & 3) + 4 * (choice >> 2)
        if reset:
            session.stream_reset(stream_id, choice)
        else:
            session.receive(stream_id, data, fin)
    closes = [t for t in session.take_transmit() if isinstance(t, CloseSession)]
    assert len(closes) <= 1 and session.closed == bool(closes)
    session.take_events()
