"""RelayCore over in-memory pipes: fan-out, late join, slow viewers, failures, limits."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from server.moq import events as ev
from server.moq.errors import ErrorCode
from server.moq.limits import MoqLimits
from server.moq.relay_core import MAX_REFUSED_SUBSCRIBES
from server.moq.session import MoqSession
from server.moq.transmit import ResetStream
from tests.moq_pipe import RelayNet


def of(events: list[Any], kind: type) -> list[Any]:
    return [e for e in events if isinstance(e, kind)]


def frames(session: MoqSession) -> list[bytes]:
    return [e.payload for e in of(session.take_events(), ev.FrameReceived)]


def serve(net: RelayNet, publisher: MoqSession) -> dict[str, int]:
    """Accept every pending subscribe at the publisher; returns track -> request id."""
    accepted = {}
    for request in of(publisher.take_events(), ev.SubscribeRequested):
        publisher.accept_subscribe(request.request_id)
        accepted[request.track] = request.request_id
    net.pump()
    return accepted


def setup(viewers: int, **options: Any) -> tuple[RelayNet, MoqSession, list[MoqSession], int]:
    """A publisher of `game` and viewers subscribed to its `video`; returns its request id."""
    net = RelayNet(**options)
    publisher = net.connect("pub")
    publisher.publish("game")
    net.pump()
    sessions = [net.connect(f"v{i}") for i in range(viewers)]
    for viewer in sessions:
        handle = viewer.request_announces("")
        net.pump()
        assert of(viewer.take_events(), ev.AnnounceReceived) == [
            ev.AnnounceReceived(handle, "game", True, 1)
        ]
        viewer.subscribe("game", "video")
    net.pump()
    requests = serve(net, publisher)
    assert list(requests) == ["video"]  # ONE upstream subscription for all viewers
    for viewer in sessions:
        assert len(of(viewer.take_events(), ev.SubscribeAccepted)) == 1
    return net, publisher, sessions, requests["video"]


def one_viewer(max_latency_ms: int) -> tuple[RelayNet, MoqSession, MoqSession, int]:
    """A publisher of `game` and one viewer `v` of its `video` with a max latency; returns
    the publisher's request id for it."""
    net = RelayNet()
    publisher = net.connect("pub")
    publisher.publish("game")
    net.pump()
    viewer = net.connect("v")
    viewer.subscribe("game", "video", max_latency_ms=max_latency_ms)
    net.pump()
    return net, publisher, viewer, serve(net, publisher)["video"]


def send_group(publisher: MoqSession, request: int, sequence: int, payloads: list[bytes]) -> int:
    stream = publisher.open_group(request, sequence)
    assert stream is not None
    for payload in payloads:
        publisher.write_frame(stream, payload)
    return stream


def test_fan_out_to_every_viewer_and_count() -> None:
    net, publisher, viewers, request = setup(3)
    stream = send_group(publisher, request, 0, [b"key", b"p1", b"p2"])
    publisher.finish_group(stream)
    net.pump()
    for viewer in viewers:
        events = viewer.take_events()
        assert of(events, ev.GroupOpened)[0].sequence == 0
        assert [e.payload for e in of(events, ev.FrameReceived)] == [b"key", b"p1", b"p2"]
        assert of(events, ev.GroupClosed)[0].complete
    stats = net.relay.stats("pub")
    assert stats is not None and (stats.frames_in, stats.bytes_in) == (3, 7)
    viewer_stats = net.relay.stats("v1")
    assert viewer_stats is not None and viewer_stats.frames_out == 3


def test_late_viewer_starts_at_the_current_group_then_goes_live() -> None:
    net, publisher, _, request = setup(1)
    old = send_group(publisher, request, 0, [b"old"])
    publisher.finish_group(old)
    stream = send_group(publisher, request, 1, [b"key", b"d1"])
    net.pump()
    late = net.connect("late")
    late.subscribe("game", "video")
    net.pump()
    publisher.write_frame(stream, b"d2")
    net.pump()
    events = late.take_events()
    assert of(events, ev.SubscribeAccepted)
    assert [e.sequence for e in of(events, ev.GroupOpened)] == [1]
    assert [e.payload for e in of(events, ev.FrameReceived)] == [b"key", b"d1", b"d2"]
    assert of(publisher.take_events(), ev.SubscribeRequested) == []  # still one upstream


def test_viewer_that_never_reads_is_skipped_while_the_other_gets_everything() -> None:
    net, publisher, (slow, fast), request = setup(2, max_backlog_bytes=2000)
    net.pipes["v0"].hold_to_client = True
    payloads = [bytes([i]) * 500 for i in range(10)]
    stream = send_group(publisher, request, 0, payloads[:1])
    for payload in payloads[1:]:  # one frame per network event, as a live encoder sends
        net.pump()
        publisher.write_frame(stream, payload)
    net.pump()
    assert net.pipes["v0"].buffered_bytes(3) <= 2000 + 600  # bounded, not 5000
    net.pipes["v0"].release()
    net.pump()
    publisher.finish_group(stream)
    send_group(publisher, request, 1, [b"key1"])
    net.pump()
    assert frames(fast) == [*payloads, b"key1"]
    events = slow.take_events()
    closed = of(events, ev.GroupClosed)
    assert closed[0].sequence == 0 and not closed[0].complete
    assert closed[0].error_code == ErrorCode.SKIPPED
    got = [(e.sequence, e.payload) for e in of(events, ev.FrameReceived)]
    assert len(got) < 11 and got[-1] == (1, b"key1")  # skipped ahead to the newest group
    stats = net.relay.stats("v0")
    assert stats is not None and stats.groups_skipped == 1


def test_viewer_past_its_max_latency_is_skipped_on_poll() -> None:
    net, publisher, viewer, request = one_viewer(max_latency_ms=100)
    net.pipes["v"].hold_to_client = True
    send_group(publisher, request, 0, [b"k"])
    net.pump()
    net.now = 0.05
    assert net.relay.poll() == set()
    net.now = 0.2
    assert net.relay.poll() == {"v", "pub"}  # the publisher is nudged for a keyframe
    net.pipes["v"].release()
    net.pump()
    closed = of(viewer.take_events(), ev.GroupClosed)
    assert closed and closed[0].error_code == ErrorCode.SKIPPED


def test_a_skipped_viewer_nudges_the_publisher_for_a_keyframe_at_most_once_a_second() -> None:
    """moq-lite cannot ask for a keyframe: the relay subscribes once more (our publisher
    starts a new subscriber at a keyframe) and cancels that as soon as it is accepted;
    the skipped viewer joins the group the keyframe opens, instead of waiting seconds."""
    net, publisher, viewer, request = one_viewer(max_latency_ms=100)
    net.pipes["v"].hold_to_client = True
    stream = send_group(publisher, request, 0, [b"k0"])
    net.pump()
    net.now = 0.2
    net.relay.poll()
    net.pump()
    nudges = of(publisher.take_events(), ev.SubscribeRequested)
    assert [(n.broadcast, n.track) for n in nudges] == [("game", "video")]
    assert nudges[0].request_id != request
    publisher.accept_subscribe(nudges[0].request_id)
    net.pump()
    cancelled = of(publisher.take_events(), ev.SubscribeCancelled)
    assert [c.request_id for c in cancelled] == [nudges[0].request_id]
    # The publisher's keyframe opens a group on the relay's subscription: the viewer
    # joins it. Nothing of the nudge's own subscription reaches anyone.
    publisher.finish_group(stream)
    send_group(publisher, request, 1, [b"k1"])
    net.pipes["v"].release()
    net.pump()
    assert frames(viewer)[-1] == b"k1"
    stats = net.relay.stats("pub")
    assert stats is not None and stats.keyframe_nudges == 1
    # Skipped again within the second: no second nudge; after it, one more.
    net.pipes["v"].hold_to_client = True
    stream = send_group(publisher, request, 2, [b"k2"])
    net.pump()
    net.now = 0.5
    net.relay.poll()
    net.pump()
    assert of(publisher.take_events(), ev.SubscribeRequested) == []
    publisher.finish_group(stream)
    net.now = 1.1
    send_group(publisher, request, 3, [b"k3"])
    net.pump()
    net.now = 1.3
    net.relay.poll()
    net.pump()
    assert len(of(publisher.take_events(), ev.SubscribeRequested)) == 1
    assert stats.keyframe_nudges == 2


def test_finished_groups_that_went_stale_are_skipped_too() -> None:
    """Groups shorter than the max latency finish before any of their frames is old:
    a viewer that stopped reading must still be skipped ahead (its finished groups reset)
    instead of being handed every stale short group, one after another."""
    net, publisher, _viewer, request = one_viewer(max_latency_ms=100)
    net.pipes["v"].hold_to_client = True
    for sequence in range(5):  # 5 groups of 2 frames, 40 ms apart: each 40 ms long
        net.now = sequence * 0.04
        stream = publisher.open_group(request, sequence)
        assert stream is not None
        for payload in (b"k%d" % sequence, b"d"):
            publisher.write_frame(stream, payload)
            net.pump()  # each frame reaches the viewer's (held) queue on its own
        publisher.finish_group(stream)
        net.pump()
    stats = net.relay.stats("v")
    assert stats is not None and stats.groups_skipped >= 1  # group 0 was 160 ms old
    net.now = 0.5
    net.relay.poll()
    net.pump()
    # Every group stream queued for the viewer was reset (after its FIN: the queued
    # bytes are dropped, not sent), so nothing 500 ms old is left to send.
    resets = [
        t.stream_id
        for t in net.pipes["v"]._held
        if isinstance(t, ResetStream) and t.error_code == ErrorCode.SKIPPED
    ]
    assert len(set(resets)) == stats.groups_skipped == 5


def test_one_session_holds_at_most_two_subscriptions_of_a_track() -> None:
    """A session that subscribes to the same track again and again is refused past two
    (a re-subscribe may overlap the old one): each would be one more copy of every frame."""
    net = RelayNet()
    publisher = net.connect("pub")
    publisher.publish("game")
    net.pump()
    viewer = net.connect("v")
    first = viewer.subscribe("game", "video")
    net.pump()
    request = serve(net, publisher)["video"]
    ids = [first] + [viewer.subscribe("game", "video") for _ in range(5)]
    net.pump()
    refused = {e.subscription_id for e in of(viewer.take_events(), ev.SubscribeClosed)}
    assert refused == set(ids[2:])
    stream = send_group(publisher, request, 0, [b"k"])
    publisher.finish_group(stream)
    net.pump()
    assert len(of(viewer.take_events(), ev.FrameReceived)) == 2
    other = net.connect("w")  # another session is not affected
    other.subscribe("game", "video")
    net.pump()
    assert net.relay.viewer_count("game", "video") == 3
    # Refused again and again: a flood, not a player; that one session is closed.
    relay_side = net.pipes["v"].server
    for _ in range(MAX_REFUSED_SUBSCRIBES):
        viewer.subscribe("game", "video")
        net.pump()
        if relay_side.closed:
            break
    assert relay_side.closed
    assert net.pipes["v"].closes["server"].error_code == ErrorCode.LIMIT_EXCEEDED
    assert net.relay.viewer_count("game", "video") == 1  # w's, untouched


def test_garbage_from_one_viewer_closes_only_that_session() -> None:
    net, publisher, (_, good), request = setup(2)
    net.pipes["v0"].server.receive(0 + 4 * 50, b"\x09garbage", False)
    net.pump()
    assert net.pipes["v0"].server.closed
    assert net.pipes["v0"].closes["server"].error_code == ErrorCode.PROTOCOL_VIOLATION
    net.disconnect("v0")
    stream = send_group(publisher, request, 0, [b"k"])
    publisher.finish_group(stream)
    net.pump()
    assert frames(good) == [b"k"]
    assert not publisher.closed and net.relay.viewer_count("game", "video") == 1


def test_subscribe_to_missing_broadcast_or_track() -> None:
    net = RelayNet()
    publisher = net.connect("pub")
    publisher.publish("game")
    viewer = net.connect("v")
    missing = viewer.subscribe("nothing", "video")
    net.pump()
    closed = of(viewer.take_events(), ev.SubscribeClosed)
    assert closed == [ev.SubscribeClosed(missing, ErrorCode.NOT_FOUND, False)]
    unknown_track = viewer.subscribe("game", "nope")
    net.pump()
    (request,) = of(publisher.take_events(), ev.SubscribeRequested)
    publisher.reject_subscribe(request.request_id, ErrorCode.NOT_FOUND)
    net.pump()
    assert viewer.take_events() == [ev.SubscribeClosed(unknown_track, ErrorCode.NOT_FOUND, False)]
    assert not viewer.closed and net.pipes["v"].closes == {}


def test_publisher_leaves_and_returns() -> None:
    net, publisher, (viewer,), request = setup(1)
    send_group(publisher, request, 7, [b"a"])
    net.pump()
    viewer.take_events()
    net.disconnect("pub")
    events = viewer.take_events()
    assert ev.AnnounceReceived(0, "game", False, 1) in events
    assert of(events, ev.SubscribeClosed) == [ev.SubscribeClosed(0, None, True)]
    assert of(events, ev.GroupClosed)[0].error_code == ErrorCode.GONE
    assert net.relay.broadcasts == {}
    publisher = net.connect("pub2")
    publisher.publish("game")
    net.pump()
    assert ev.AnnounceReceived(0, "game", True, 1) in viewer.take_events()
    viewer.subscribe("game", "video")
    net.pump()
    request = serve(net, publisher)["video"]
    send_group(publisher, request, 0, [b"again"])
    net.pump()
    assert frames(viewer) == [b"again"]


def test_last_viewer_leaving_ends_the_upstream_subscription() -> None:
    net, publisher, (viewer,), request = setup(1)
    viewer.unsubscribe(0)
    net.pump()
    assert ev.SubscribeCancelled(request, None) in publisher.take_events()
    assert net.relay.viewer_count("game", "video") == 0


def test_subscribe_storm_is_bounded_by_limits() -> None:
    net = RelayNet()
    publisher = net.connect("pub")
    publisher.publish("game")
    net.pump()
    storm = net.connect("storm", limits=MoqLimits(max_subscriptions=16))
    calm = net.connect("calm")
    for _ in range(200):
        storm.subscribe("game", "video")
    calm.subscribe("game", "video")
    net.pump()
    assert net.pipes["storm"].closes["server"].error_code == ErrorCode.LIMIT_EXCEEDED
    events = publisher.take_events()
    # The storm's share of the upstream was released when its session closed.
    live = len(of(events, ev.SubscribeRequested)) - len(of(events, ev.SubscribeCancelled))
    assert live == 1
    request = next(e for e in reversed(events) if isinstance(e, ev.SubscribeRequested))
    publisher.accept_subscribe(request.request_id)
    net.pump()
    send_group(publisher, request.request_id, 0, [b"k"])
    net.pump()
    assert frames(calm) == [b"k"]


@settings(max_examples=60, deadline=None)
@given(
    garbage=st.binary(min_size=1, max_size=40),
    when=st.integers(0, 4),
    bidi=st.booleans(),
    victim=st.sampled_from(["v0", "pub"]),
)
def test_relay_survives_garbage_at_any_time(
    garbage: bytes, when: int, bidi: bool, victim: str
) -> None:
    """Garbage into one relay-side session mid-stream: no exception, others unharmed."""
    net, publisher, (_, good), request = setup(2)
    stream = send_group(publisher, request, 0, [])
    sent = []
    for i in range(5):
        if i == when:
            # Peer-initiated ids as the relay (server) sees them: client bidi 0 mod 4, uni 2.
            net.pipes[victim].server.receive(4 * 40 + (0 if bidi else 2), garbage, False)
        payload = bytes([i]) * 3
        publisher.write_frame(stream, payload)
        sent.append(payload)
        net.pump()
    events = good.take_events()
    received = [e.payload for e in of(events, ev.FrameReceived)]
    if net.pipes[victim].server.closed and victim == "pub":
        assert received == sent[:when]
        assert of(events, ev.SubscribeClosed) == [ev.SubscribeClosed(0, None, True)]
    else:
        assert received == sent
