"""A viewer out of QUIC stream credit (the peer's MAX_STREAMS) is skipped ahead, never sent
a frame that breaks QUIC: no group stream is opened past the credit, and a reset of a
stream aioquic still holds as blocked waits until the credit covers it.

Without that, aioquic sends RESET_STREAM for a stream the peer has not let us open, and a
strict peer (aioquic itself) closes the connection with STREAM_LIMIT_ERROR.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from aioquic.quic.connection import QuicConnection

from server.moq import events as ev
from server.moq.errors import ErrorCode
from server.moq.session import MoqSession
from server.moq.transmit import SendData
from server.quic import client as quic_client
from server.quic.certs import CertBundle, generate_cert
from tests.moq_pipe import Pipe, RelayNet, StreamIds
from tests.relay_harness import Publisher, Viewer, relay_link, run_bounded, running_relay, until

# Uni streams the starved viewer lets the relay open: 3 go to HTTP/3 (control, QPACK
# encoder and decoder), which leaves 5 for groups until it reads and grants more.
SMALL_CREDIT = 8


def of(events: list[Any], kind: type) -> list[Any]:
    return [e for e in events if isinstance(e, kind)]


# ----------------------------------------------------------------------- sans-IO


class Credit:
    """A can_open_stream the test turns on and off; counts the streams really opened."""

    def __init__(self) -> None:
        self.available = True
        self.opened: list[int] = []
        self._ids = StreamIds(False)

    def can_open(self, is_unidirectional: bool) -> bool:
        return self.available

    def open(self, is_unidirectional: bool) -> int:
        stream_id = self._ids.open(is_unidirectional)
        self.opened.append(stream_id)
        return stream_id


def test_open_group_without_credit_opens_nothing() -> None:
    credit = Credit()
    server = MoqSession(is_client=False, open_stream=credit.open, can_open_stream=credit.can_open)
    client = MoqSession(is_client=True, open_stream=StreamIds(True).open)
    server.publish("game")
    client.subscribe("game", "video")
    for t in client.take_transmit():
        assert isinstance(t, SendData)
        server.receive(t.stream_id, t.data, t.end_stream)
    (request,) = of(server.take_events(), ev.SubscribeRequested)
    assert server.accept_subscribe(request.request_id)
    server.take_transmit()

    credit.available = False
    assert server.open_group(request.request_id, 0) is None
    assert credit.opened == [] and server.take_transmit() == []
    assert not server.closed  # no credit is no error: the caller drops the group

    credit.available = True
    stream = server.open_group(request.request_id, 1)
    assert stream is not None and credit.opened == [stream]
    assert server.write_frame(stream, b"key")


class _CreditPipe(Pipe):
    """A Pipe whose relay side asks `credit` before opening a stream."""

    def __init__(self, credit: Credit) -> None:
        self.credit = credit
        super().__init__()

    def __post_init__(self) -> None:
        super().__post_init__()
        self.server = MoqSession(
            is_client=False, open_stream=self.credit.open, can_open_stream=self.credit.can_open
        )


def test_relay_skips_groups_while_a_viewer_has_no_credit() -> None:
    net = RelayNet()
    publisher = net.connect("pub")
    publisher.publish("game")
    net.pump()
    credit = Credit()
    starved = net.pipes["v"] = _CreditPipe(credit)
    net.relay.add_connection("v", starved.server)
    net.pump()
    viewer = starved.client
    viewer.subscribe("game", "video")
    net.pump()
    (request,) = of(publisher.take_events(), ev.SubscribeRequested)
    publisher.accept_subscribe(request.request_id)
    net.pump()
    viewer.take_events()

    def group(sequence: int, payloads: list[bytes]) -> None:
        stream = publisher.open_group(request.request_id, sequence)
        assert stream is not None
        for payload in payloads:
            publisher.write_frame(stream, payload)
            net.pump()
        publisher.finish_group(stream)
        net.pump()

    credit.available = False
    group(0, [b"k0", b"d0"])
    group(1, [b"k1"])
    stats = net.relay.stats("v")
    assert stats is not None and stats.groups_skipped == 2
    assert of(viewer.take_events(), ev.FrameReceived) == []
    # Credit is back mid-group: the viewer waits for the next group's start.
    stream = publisher.open_group(request.request_id, 2)
    assert stream is not None
    publisher.write_frame(stream, b"k2")
    net.pump()
    credit.available = True
    publisher.write_frame(stream, b"d2")
    publisher.finish_group(stream)
    net.pump()
    group(3, [b"k3", b"d3"])
    events = viewer.take_events()
    assert [(e.sequence, e.payload) for e in of(events, ev.FrameReceived)] == [
        (3, b"k3"),
        (3, b"d3"),
    ]
    assert of(events, ev.GroupClosed)[0].complete
    assert stats.groups_skipped == 3  # group 2 was skipped at its start, before credit
    assert not viewer.closed and not starved.server.closed


# ----------------------------------------------------------------------- real QUIC


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@pytest.fixture(autouse=True)
def no_relay_errors(caplog: pytest.LogCaptureFixture) -> Iterator[None]:
    caplog.set_level(logging.WARNING)
    yield
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]


run = functools.partial(run_bounded, timeout=20.0)


@contextmanager
def small_uni_credit(monkeypatch: pytest.MonkeyPatch, credit: int) -> Iterator[None]:
    """Client connections made inside allow the server only `credit` uni streams at first
    (aioquic's default is 128); more come as the client finishes streams."""

    class SmallCredit(QuicConnection):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            # Private: the Limit aioquic advertises as initial_max_streams_uni.
            limit = self._local_max_streams_uni
            limit.value = limit.sent = credit

    with monkeypatch.context() as patch:
        patch.setattr(quic_client, "QuicConnection", SmallCredit)
        yield


def first_indexes(viewer: Viewer) -> dict[int, int]:
    """Group sequence -> index (in its group) of the first frame received of it."""
    first: dict[int, int] = {}
    for f in viewer.frames:
        assert f.sequence == f.group, "GROUP header and payload disagree"
        first.setdefault(f.sequence, f.index)
    return first


def test_stalled_viewer_out_of_credit_is_skipped_not_disconnected(
    cert: CertBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    async def body() -> None:
        # A small backlog bound: the stalled viewer's unsent groups pass it within a few
        # groups, so the relay skips groups for it all through the stall (what used to
        # reset streams past its credit).
        async with running_relay(cert, max_backlog_bytes=20_000) as relay:
            publisher = Publisher()
            await publisher.start(relay.port, cert)
            await until(lambda: "game" in relay.core.broadcasts)
            fast, slow = Viewer(), Viewer()
            await fast.connect(relay.port, cert)
            with small_uni_credit(monkeypatch, SMALL_CREDIT):
                await slow.connect(relay.port, cert)
            for viewer in (fast, slow):
                await viewer.subscribed()
            slow_id, slow_link = relay_link(relay, slow)

            # 1.5 s of 20 short groups a second while the slow viewer reads nothing: no
            # acks, no MAX_STREAMS; its 5 group streams are used up at once.
            resume = slow.stall()
            await publisher.stream(90, fps=60, group_every=3, size=1500)
            stats = relay.core.stats(slow_id)
            assert stats is not None
            skipped_in_stall = stats.groups_skipped
            blocked_in_stall = len(slow_link.wt.conn.quic._streams_blocked_uni)
            resume()

            # It reads again: later groups reach it whole, from their first frame.
            streaming = asyncio.create_task(publisher.stream(600, fps=60, group_every=3, size=1500))

            def whole_later_groups() -> int:
                indexes: dict[int, list[int]] = {}
                for f in slow.frames:
                    indexes.setdefault(f.group, []).append(f.index)
                return sum(g >= 30 and i == [0, 1, 2] for g, i in indexes.items())

            await slow.until(lambda: whole_later_groups() >= 10 or slow.moq_link.closed, 10)
            streaming.cancel()
            assert not slow.moq_link.closed, slow.moq_link.closed_reason
            assert not slow_link.closed, slow_link.closed_reason
            assert skipped_in_stall >= 20, skipped_in_stall
            assert blocked_in_stall == 0  # no stream was opened past its credit
            await until(lambda: len(fast.frames) >= publisher.number)

            assert all(index == 0 for index in first_indexes(slow).values())
            assert sorted(fast.numbers()) == list(range(publisher.number))
            per_group: dict[int, list[int]] = {}
            for f in fast.frames:
                per_group.setdefault(f.group, []).append(f.number)
            assert all(numbers == sorted(numbers) for numbers in per_group.values())
            assert all(index == 0 for index in first_indexes(fast).values())
            later = sorted({f.group for f in slow.frames if f.group >= 30})
            print(
                f"slow viewer: {stats.groups_skipped} groups skipped ({skipped_in_stall} in"
                f" the 1.5 s stall, 30 groups sent then); {len(slow.frames)} frames,"
                f" groups {later[0]}..{later[-1]} after it, {whole_later_groups()} whole;"
                f" fast viewer: {len(fast.frames)}/{publisher.number} frames"
            )

    run(body(), timeout=20)


def test_reset_of_a_blocked_stream_waits_for_credit(
    cert: CertBundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Defence in depth: streams opened past the credit by any path and then reset."""

    async def body() -> None:
        async with running_relay(cert) as relay:
            viewer = Viewer()
            with small_uni_credit(monkeypatch, SMALL_CREDIT):
                await viewer.connect(relay.port, cert)
            _, link = relay_link(relay, viewer)
            quic = link.wt.conn.quic
            # The relay already used 3 of the credit for HTTP/3: these 5 fit, 7 wait.
            streams = [link.wt.open_stream(True) for _ in range(12)]
            assert len(quic._streams_blocked_uni) == 7
            assert not link.wt.can_open_stream(True)
            for stream_id in streams:
                link.wt.send(stream_id, b"x" * 5000)
                link.wt.reset_stream(stream_id, ErrorCode.SKIPPED)
            # Nothing of theirs is kept for the wait: not counted, not held by aioquic.
            assert sum(link.wt.buffered_bytes(s) for s in streams) == 0
            assert sum(len(quic._streams[s].sender._buffer) for s in streams) == 0
            # The viewer finishes the 5 reset streams it may see, grants more, and the held
            # resets follow: every stream ends, and the connection stays up.
            await until(
                lambda: viewer.moq_link.closed or not any(s in quic._streams for s in streams)
            )
            assert not viewer.moq_link.closed, viewer.moq_link.closed_reason
            assert not quic._streams_blocked_uni
            assert link.wt.can_open_stream(True)
            await asyncio.sleep(0.2)
            assert not viewer.moq_link.closed, viewer.moq_link.closed_reason
            assert not link.closed, link.closed_reason

    run(body(), timeout=20)
