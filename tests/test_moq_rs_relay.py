"""Scale-out proof: our publisher and our viewers through moq-dev's Rust relay core.

The relay here is ``moq.Server`` from the ``moq-rs`` package (the Rust core that
moq-dev's ``moq-relay`` is built on), run in-process on this test's asyncio loop
with one shared origin: what a publisher announces is what subscribers find, as
in moq-relay. Nothing of upcast's own relay is involved: if these frames arrive
intact and in order, a provider can put moq-relay (or a moq-lite CDN) in front of
upcast by changing only the ``--relay`` URL.

Negotiation: the server offers moq-lite-01..07 and moqt-15..22 through
``wt-available-protocols``; our client offers only moq-lite-03 (what ``@moq/lite``
0.2 speaks) and the test checks that is what was chosen.

Outside CI the test skips when moq-rs is not installed; under ``CI=true`` (the dev
extras install it) a missing package fails instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass
from typing import Any

import pytest

from server.frames.frame import FrameMeta, Size
from server.loadtest.synthetic import SyntheticPublisher, SyntheticSettings
from server.loadtest.viewer import CATALOG_TRACK, TIMING_TRACK, LoadViewer, ViewerConfig
from server.media.encode import EncodedFrame
from server.moq.events import FrameReceived
from server.quic.moq_link import MoqLink

if os.environ.get("CI"):
    import moq
else:
    moq = pytest.importorskip("moq", reason="moq-rs not installed: pip install -e '.[dev]'")

SIZE = Size(320, 180)
FPS = 30.0
WATCH_S = 2.5
GOP_S = 0.5
GOP_FRAMES = int(GOP_S * FPS)


@dataclass
class RustRelay:
    url: str
    cert_hash_hex: str
    accepted: int = 0


@contextlib.asynccontextmanager
async def rust_relay() -> AsyncIterator[RustRelay]:
    """moq.Server on a free UDP port with a generated certificate; sessions are held
    until they close (dropping a moq.Session closes the connection)."""
    async with moq.Server("127.0.0.1:0", tls_generate=["localhost"]) as server:
        port = int(server.local_addr.rsplit(":", 1)[1])
        relay = RustRelay(f"https://127.0.0.1:{port}/", server.cert_fingerprints()[0])
        held: set[asyncio.Task[None]] = set()

        async def hold(request: Any) -> None:
            session = await request.accept()
            relay.accepted += 1
            # A peer's close surfaces as a moq error here; it is the normal end.
            with contextlib.suppress(moq.Error):
                await session.closed()

        async def accept_loop() -> None:
            async for request in server:
                task = asyncio.create_task(hold(request))
                held.add(task)
                task.add_done_callback(held.discard)

        acceptor = asyncio.create_task(accept_loop())
        try:
            yield relay
        finally:
            acceptor.cancel()
            for task in list(held):
                task.cancel()
            await asyncio.gather(acceptor, *held, return_exceptions=True)


class RecordingViewer(LoadViewer):
    """Our load-test viewer, keeping every payload it receives per track."""

    def __init__(self, index: int, config: ViewerConfig) -> None:
        now = time.monotonic()
        super().__init__(index, config, window=(now, now + 3600.0))
        self.received: dict[str, list[bytes]] = {}

    def _on_frame(self, link: MoqLink, event: FrameReceived) -> None:
        track = self._tracks.get(event.subscription_id)
        if track is not None:
            self.received.setdefault(track, []).append(bytes(event.payload))
        super()._on_frame(link, event)


def record_published(publisher: SyntheticPublisher) -> list[EncodedFrame]:
    """Every frame the publisher hands to its broadcast, in order."""
    published: list[EncodedFrame] = []
    original = publisher.broadcast.publish_frame

    def publish_frame(encoded: EncodedFrame, meta: FrameMeta) -> None:
        published.append(encoded)
        original(encoded, meta)

    publisher.broadcast.publish_frame = publish_frame  # type: ignore[method-assign]
    return published


def run(coro: Coroutine[Any, Any, Any], timeout: float = 40.0) -> Any:
    async def bounded() -> Any:
        async with asyncio.timeout(timeout):
            return await coro

    return asyncio.run(bounded())


def assert_intact_run(received: list[bytes], published: list[EncodedFrame]) -> int:
    """``received`` is a contiguous run of ``published`` fragments starting at a
    keyframe, byte for byte; returns the index of its first frame."""
    assert received, "no video frame arrived through the Rust relay"
    fragments = [e.fragment for e in published]
    starts = [i for i, f in enumerate(fragments) if f == received[0]]
    assert starts, "the first frame received was never published"
    start = starts[0]
    assert published[start].keyframe, "a viewer must join at a group (keyframe) start"
    expected = fragments[start : start + len(received)]
    assert len(expected) == len(received), "received more frames than were published"
    for i, (got, want) in enumerate(zip(received, expected, strict=True)):
        assert got == want, f"frame {start + i} differs after the relay"
    return start


async def watch_through_rust_relay() -> tuple[
    RustRelay, list[EncodedFrame], list[RecordingViewer], list[str | None]
]:
    async with rust_relay() as relay:
        publisher = SyntheticPublisher(
            SyntheticSettings(
                relay.url, SIZE, FPS, gop_seconds=GOP_S, cert_hash_hex=relay.cert_hash_hex
            )
        )
        published = record_published(publisher)
        stop = asyncio.Event()
        publishing = asyncio.create_task(publisher.run(stop))
        config = ViewerConfig(relay.url, "game", relay.cert_hash_hex, connect_timeout_s=10.0)
        viewers = [RecordingViewer(0, config), RecordingViewer(1, config)]
        try:
            await asyncio.wait_for(publisher.connected.wait(), 10.0)
            await viewers[0].connect()
            await asyncio.sleep(WATCH_S / 2)
            await viewers[1].connect()  # joins mid-stream: starts at the next group
            await asyncio.sleep(WATCH_S / 2)
            protocols = [v.link.wt.protocol if v.link else None for v in viewers]
        finally:
            for viewer in viewers:
                viewer.close()
            stop.set()
            await publishing
        return relay, published, viewers, protocols


def test_our_publisher_and_viewers_through_the_moq_rs_relay() -> None:
    relay, published, viewers, protocols = run(watch_through_rust_relay())

    assert relay.accepted == 3  # the publisher and two viewers, all through Rust
    assert protocols == ["moq-lite-03", "moq-lite-03"]
    for viewer in viewers:
        stats = viewer.stats
        assert stats.connected and stats.error is None and stats.catalog, stats.summary()
        assert viewer._video_track is not None
        video = viewer.received[viewer._video_track]
        # At 30 fps, each viewer watched >= 1.25 s minus a join of at most one group.
        assert len(video) >= 20, stats.summary()
        start = assert_intact_run(video, published)
        assert stats.lost == 0 and stats.bad_fragments == 0

        catalog = json.loads(viewer.received[CATALOG_TRACK][0])
        assert next(iter(catalog["video"]["renditions"].values()))["codedWidth"] == SIZE.width

        # The timing track went through the same relay and counts frames without gaps.
        counts = [json.loads(p)["n"] for p in viewer.received[TIMING_TRACK]]
        assert counts == list(range(counts[0], counts[0] + len(counts)))
        # Both tracks were subscribed together; their first groups are at most one apart.
        assert abs(counts[0] - start) <= GOP_FRAMES
    assert viewers[1].received["video"][0] != viewers[0].received["video"][0]
