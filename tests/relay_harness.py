"""Loopback harness for relay end-to-end tests: a real Relay, publisher and viewers over QUIC.

Everything runs in the test's own event loop (started with `asyncio.run`): the Relay on
port 0 with a freshly generated certificate, a Python publisher of broadcast `game` that
answers subscribes for its tracks, and viewers that subscribe and record every frame.

A frame's payload starts with a header (group, index in group, frame number, send time)
so a viewer can check order, keyframe boundaries (index 0 opens each group) and latency
without any shared state with the publisher.
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

from server.auth import Authorizer
from server.moq import events as ev
from server.moq.errors import ErrorCode
from server.moq.events import Event
from server.quic.certs import CertBundle
from server.quic.client import WtClientConnection
from server.quic.moq_link import MoqLink, connect_moq
from server.relay.relay import Relay, RelayConfig

HEADER = struct.Struct(">IIId")  # group, index in group, frame number, send time (monotonic)


def make_frame(group: int, index: int, number: int, size: int) -> bytes:
    header = HEADER.pack(group, index, number, time.monotonic())
    return header + bytes(max(0, size - len(header)))


@dataclass(frozen=True)
class Received:
    subscription_id: int
    sequence: int  # from the GROUP header on the wire
    group: int  # from the payload header (what the publisher meant)
    index: int
    number: int
    sent: float
    received: float
    size: int

    @property
    def latency(self) -> float:
        return self.received - self.sent


@asynccontextmanager
async def running_relay(cert: CertBundle, **config: Any) -> AsyncIterator[Relay]:
    """A relay on port 0; open (the `--no-auth` relay) unless `authorizer` is given:
    these tests are about fan-out, test_relay_auth.py about tokens."""
    config.setdefault("authorizer", Authorizer.open_relay())
    relay = Relay(RelayConfig(host="::", port=0, **config), cert)
    await relay.start()
    try:
        yield relay
    finally:
        await relay.close()


class Peer:
    """One moq-lite client session to the relay; records every event it is given."""

    def __init__(self) -> None:
        self.link: MoqLink | None = None
        self.events: list[Event] = []
        self.changed = asyncio.Event()

    async def connect(self, port: int, cert: CertBundle, token: str | None = None) -> None:
        self.link = await connect_moq(
            f"https://localhost:{port}/",
            on_events=self._on_events,
            on_closed=lambda link, reason: self.changed.set(),
            cert_hash_hex=cert.sha256_hex,
            token=token,
        )

    @property
    def moq_link(self) -> MoqLink:
        assert self.link is not None, "not connected"
        return self.link

    @property
    def local_port(self) -> int:
        transport = self.moq_link.wt.conn._transport
        assert transport is not None
        return int(transport.get_extra_info("sockname")[1])

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def _on_events(self, link: MoqLink, events: list[Event]) -> None:
        self.link = link  # events can come before connect_moq returns (the relay's interest)
        self.events.extend(events)
        for event in events:
            self.handle(event)
        self.changed.set()

    def handle(self, event: Event) -> None:
        """Subclasses react to one event (commands are flushed by the link's pump)."""

    async def until(self, cond: Callable[[], bool], timeout: float = 5.0) -> None:
        async with asyncio.timeout(timeout):
            while not cond():
                self.changed.clear()
                await self.changed.wait()

    def abort(self) -> None:
        """Vanish abruptly: CONNECTION_CLOSE without a WebTransport close, socket gone."""
        conn = self.moq_link.wt.conn
        assert isinstance(conn, WtClientConnection)
        conn.abort()

    def stall(self) -> Callable[[], None]:
        """Drop every datagram from now on (a viewer that never reads: nothing is acked,
        no flow-control credit comes back). Returns a function that resumes reading."""
        conn = self.moq_link.wt.conn
        real = conn.datagram_received
        conn.datagram_received = lambda data, addr: None  # type: ignore[method-assign]

        def resume() -> None:
            conn.datagram_received = real  # type: ignore[method-assign]

        return resume

    def close(self) -> None:
        if self.link is not None and not self.link.closed:
            self.link.close(0, "done")


class Publisher(Peer):
    """Publishes `broadcast` with `tracks`; only `video` carries frames.

    A subscriber that arrives mid-group gets the current group from its first frame,
    as a real publisher (hang) does. Unknown tracks are refused with NOT_FOUND.
    """

    def __init__(self, broadcast: str = "game", tracks: tuple[str, ...] = ("video",)) -> None:
        super().__init__()
        self.broadcast = broadcast
        self.tracks = tracks
        self.requests: dict[int, str] = {}  # live request id -> track
        self.subscribe_count = 0
        self.open: dict[int, int] = {}  # request id -> stream of the current group
        self.group = -1
        self.index = 0
        self.number = 0
        self.current: list[bytes] = []  # frames of the current group so far

    async def start(self, port: int, cert: CertBundle, token: str | None = None) -> None:
        await self.connect(port, cert, token)
        self.moq_link.moq.publish(self.broadcast)
        self.moq_link.flush()

    def handle(self, event: Event) -> None:
        moq = self.moq_link.moq
        if isinstance(event, ev.SubscribeRequested):
            self.subscribe_count += 1
            if event.broadcast != self.broadcast or event.track not in self.tracks:
                moq.reject_subscribe(event.request_id, ErrorCode.NOT_FOUND)
                return
            moq.accept_subscribe(event.request_id)
            self.requests[event.request_id] = event.track
            if event.track == "video" and self.current:
                self._open_group(event.request_id)
                for frame in self.current:
                    moq.write_frame(self.open[event.request_id], frame)
        elif isinstance(event, ev.SubscribeCancelled):
            self.requests.pop(event.request_id, None)
            self.open.pop(event.request_id, None)
        elif (
            isinstance(event, ev.GroupCancelled)
            and self.open.get(event.request_id) == event.stream_id
        ):
            del self.open[event.request_id]

    def _video_requests(self) -> list[int]:
        return [r for r, track in self.requests.items() if track == "video"]

    def _open_group(self, request_id: int) -> None:
        stream = self.moq_link.moq.open_group(request_id, self.group)
        if stream is not None:
            self.open[request_id] = stream

    def end_group(self) -> None:
        for stream in self.open.values():
            self.moq_link.moq.finish_group(stream)
        self.open.clear()
        self.current = []
        self.moq_link.flush()

    def send_frame(self, size: int, *, new_group: bool = False) -> bytes:
        """One video frame to every subscriber; `new_group` starts a group (a keyframe)."""
        moq = self.moq_link.moq
        if new_group or self.group < 0:
            self.end_group()
            self.group += 1
            self.index = 0
            for request_id in self._video_requests():
                self._open_group(request_id)
        frame = make_frame(self.group, self.index, self.number, size)
        self.current.append(frame)
        for stream in self.open.values():
            moq.write_frame(stream, frame)
        self.index += 1
        self.number += 1
        self.moq_link.flush()
        return frame

    async def stream(
        self,
        count: int,
        *,
        fps: float,
        group_every: int,
        size: int | Callable[[int], int] = 2000,
    ) -> None:
        """`count` frames paced at `fps` on an absolute schedule (no drift)."""
        start = time.monotonic()
        for i in range(count):
            delay = start + i / fps - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            frame_size = size(self.number) if callable(size) else size
            self.send_frame(frame_size, new_group=self.index >= group_every)
        self.end_group()


class Viewer(Peer):
    """Subscribes and records every frame (with arrival time) and group event."""

    def __init__(self) -> None:
        super().__init__()
        self.frames: list[Received] = []

    def handle(self, event: Event) -> None:
        if isinstance(event, ev.FrameReceived):
            group, index, number, sent = HEADER.unpack_from(event.payload)
            self.frames.append(
                Received(
                    event.subscription_id,
                    event.sequence,
                    group,
                    index,
                    number,
                    sent,
                    time.monotonic(),
                    len(event.payload),
                )
            )

    def subscribe(self, broadcast: str = "game", track: str = "video", **options: Any) -> int:
        subscription_id = self.moq_link.moq.subscribe(broadcast, track, **options)
        self.moq_link.flush()
        return subscription_id

    def unsubscribe(self, subscription_id: int) -> None:
        self.moq_link.moq.unsubscribe(subscription_id)
        self.moq_link.flush()

    def request_announces(self, prefix: str = "") -> int:
        handle = self.moq_link.moq.request_announces(prefix)
        self.moq_link.flush()
        return handle

    def accepted(self, subscription_id: int) -> bool:
        return any(e.subscription_id == subscription_id for e in self.of(ev.SubscribeAccepted))

    def got_frame(self, subscription_id: int) -> bool:
        return any(f.subscription_id == subscription_id for f in self.frames)

    def subscription_ended(self, subscription_id: int) -> bool:
        return self.closed_subscription(subscription_id) is not None

    async def until_count(self, count: int, timeout: float = 5.0) -> None:
        await self.until(lambda: len(self.frames) >= count, timeout)

    def closed_subscription(self, subscription_id: int) -> ev.SubscribeClosed | None:
        found = [e for e in self.of(ev.SubscribeClosed) if e.subscription_id == subscription_id]
        return found[0] if found else None

    def numbers(self, subscription_id: int | None = None) -> list[int]:
        return [
            f.number
            for f in self.frames
            if subscription_id is None or f.subscription_id == subscription_id
        ]

    async def subscribed(self, broadcast: str = "game", track: str = "video") -> int:
        subscription_id = self.subscribe(broadcast, track)
        await self.until(lambda: self.accepted(subscription_id))
        return subscription_id


def relay_link(relay: Relay, peer: Peer) -> tuple[int, MoqLink]:
    """The relay's side of a peer's session (matched by the peer's UDP port)."""
    port = peer.local_port
    for conn_id, link in relay.links.items():
        if link.wt.remote_address[1] == port:
            return conn_id, link
    raise LookupError(f"no relay session for local port {port}")


def send_buffer_bytes(link: MoqLink) -> int:
    """Bytes aioquic really holds in send buffers for this session, reset streams
    included (total_buffered counts a reset stream as 0 even while it keeps its data)."""
    quic = link.wt.conn.quic
    return sum(len(stream.sender._buffer) for stream in quic._streams.values())


async def connected_viewers(port: int, cert: CertBundle, count: int) -> list[Viewer]:
    viewers = [Viewer() for _ in range(count)]
    await asyncio.gather(*(v.connect(port, cert) for v in viewers))
    return viewers


def run_bounded(coro: Coroutine[Any, Any, None], timeout: float = 20.0) -> None:
    """Run a test's coroutine in a fresh event loop, failing it after `timeout` seconds
    instead of letting a stuck peer hang the suite."""

    async def bounded() -> None:
        async with asyncio.timeout(timeout):
            await coro

    asyncio.run(bounded())


async def until(cond: Callable[[], bool], timeout: float = 5.0, step: float = 0.01) -> None:
    """Poll a condition on state no single peer signals (the relay's core, say)."""
    async with asyncio.timeout(timeout):
        while not cond():
            await asyncio.sleep(step)
