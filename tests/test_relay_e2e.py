"""The relay over real QUIC on loopback: fan-out, late join, bad and slow viewers, churn.

Each test runs one event loop (asyncio.run) holding the Relay (port 0), a Python publisher
of `game`/`video` and viewers (tests/relay_harness.py), bounded by asyncio.timeout.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import random
from functools import partial
from typing import Any

import pytest

from server.moq import events as ev
from server.moq.errors import ErrorCode
from server.quic.certs import CertBundle, generate_cert
from server.quic.http_fetch import http_get
from server.relay.relay import Relay
from tests.relay_harness import (
    Publisher,
    Viewer,
    connected_viewers,
    relay_link,
    run_bounded,
    running_relay,
    send_buffer_bytes,
    until,
)


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@pytest.fixture(autouse=True)
def no_relay_errors(caplog: pytest.LogCaptureFixture) -> Any:
    """Whatever a peer does, nothing in the relay or the adapters logs an error."""
    caplog.set_level(logging.WARNING)
    yield
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]


run = functools.partial(run_bounded, timeout=20.0)


async def start_publisher(relay: Relay, cert: CertBundle) -> Publisher:
    publisher = Publisher()
    await publisher.start(relay.port, cert)
    await until(lambda: "game" in relay.core.broadcasts)
    return publisher


def in_order(viewer: Viewer, expected: range, subscription_id: int | None = None) -> bool:
    """Exactly the frames `expected`, each group's in order. Groups travel on separate
    QUIC streams, so frames of two groups in flight at once may interleave."""
    got = viewer.numbers(subscription_id)
    per_group: dict[int, list[int]] = {}
    for f in viewer.frames:
        if subscription_id is None or f.subscription_id == subscription_id:
            per_group.setdefault(f.group, []).append(f.number)
    ordered = all(numbers == sorted(numbers) for numbers in per_group.values())
    return ordered and sorted(got) == list(expected) and len(got) == len(expected)


def groups_start_at_keyframes(viewer: Viewer, subscription_id: int = 0) -> bool:
    """Every group stream's first frame is the publisher's first of that group."""
    first: dict[int, int] = {}
    for f in viewer.frames:
        if f.subscription_id == subscription_id:
            assert f.sequence == f.group, "GROUP header and payload disagree"
            first.setdefault(f.sequence, f.index)
    return all(index == 0 for index in first.values())


# ---------------------------------------------------------------------------- 1


def test_fan_out_to_three_viewers_one_upstream(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            viewers = await connected_viewers(relay.port, cert, 3)
            subs = [v.subscribe() for v in viewers]
            for viewer, sub in zip(viewers, subs, strict=True):
                await viewer.until(partial(viewer.accepted, sub))
            count = 90
            await publisher.stream(count, fps=240, group_every=10, size=3000)
            for viewer in viewers:
                await viewer.until_count(count)
                assert in_order(viewer, range(count))  # all, in order
                assert groups_start_at_keyframes(viewer)
                closed = viewer.of(ev.GroupClosed)
                assert len(closed) == count // 10 and all(c.complete for c in closed)
            assert publisher.subscribe_count == 1  # ONE upstream subscription
            for viewer in viewers:
                viewer.close()
            publisher.close()

    run(body())


def test_late_group_reaches_viewers_already_following(cert: CertBundle) -> None:
    """QUIC does not order streams: a group whose first packet was lost shows up after a
    newer one. Viewers that were following get it; one that joined at the newer group not."""

    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            following = Viewer()
            await following.connect(relay.port, cert)
            await following.subscribed()
            publisher.send_frame(1000)  # group 0
            publisher.end_group()
            await following.until_count(1)
            moq = publisher.moq_link.moq
            (request,) = publisher.requests
            late = moq.open_group(request, 2)  # group 2 overtakes group 1
            assert late is not None
            moq.write_frame(late, b"g2".ljust(100, b"."))
            publisher.moq_link.flush()
            await following.until(lambda: len(following.of(ev.GroupOpened)) == 2)
            joiner = Viewer()
            await joiner.connect(relay.port, cert)
            await joiner.subscribed()
            await joiner.until(lambda: len(joiner.of(ev.GroupOpened)) == 1)
            older = moq.open_group(request, 1)
            assert older is not None
            moq.write_frame(older, b"g1".ljust(100, b"."))
            for stream in (older, late):
                moq.finish_group(stream)
            publisher.moq_link.flush()
            await following.until(lambda: len(following.of(ev.GroupClosed)) == 3)
            assert [e.sequence for e in following.of(ev.GroupOpened)] == [0, 2, 1]
            await joiner.until(lambda: len(joiner.of(ev.GroupClosed)) == 1)
            await asyncio.sleep(0.05)
            assert [e.sequence for e in joiner.of(ev.GroupOpened)] == [2]

    run(body())


# ---------------------------------------------------------------------------- 2


def test_viewer_joining_mid_group_starts_at_its_keyframe_at_once(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            first = Viewer()
            await first.connect(relay.port, cert)
            await first.subscribed()
            for i in range(14):  # group 0: frames 0-9, group 1: frames 10-13 so far
                publisher.send_frame(2000, new_group=i % 10 == 0)
            await first.until(lambda: len(first.frames) == 14)
            # The publisher is quiet now: what the late viewer gets comes from the relay.
            late = Viewer()
            await late.connect(relay.port, cert)
            await late.subscribed()
            await late.until(lambda: len(late.frames) == 4, timeout=1.0)
            assert [(f.group, f.index) for f in late.frames] == [(1, i) for i in range(4)]
            for i in range(14, 25):
                publisher.send_frame(2000, new_group=i % 10 == 0)
            await late.until(lambda: len(late.frames) == 15)
            assert in_order(late, range(10, 25))
            assert groups_start_at_keyframes(late)
            assert publisher.subscribe_count == 1  # served from the relay's cache
            # With no viewer left the upstream goes; a newcomer mid-group makes the relay
            # subscribe again and the publisher's replay starts at the keyframe.
            first.unsubscribe(0)
            late.unsubscribe(0)
            await until(lambda: not publisher.requests)
            for _ in range(25, 27):
                publisher.send_frame(2000)
            third = Viewer()
            await third.connect(relay.port, cert)
            await third.subscribed()
            await third.until(lambda: len(third.frames) == 7, timeout=1.0)
            assert in_order(third, range(20, 27))
            assert publisher.subscribe_count == 2

    run(body())


# ---------------------------------------------------------------------------- 3


# Publisher, relay and viewers share one process and one core: on a quiet machine frames
# take 1-20 ms end to end, but on a loaded 2-core machine the loop falls behind for a few
# hundred ms whatever the relay does. "On time" is what a player's jitter buffer absorbs.
ON_TIME_S = 0.2


def on_time(viewer: Viewer, limit_s: float = ON_TIME_S) -> float:
    """Fraction of the viewer's frames that arrived within `limit_s` of being published."""
    return sum(f.latency <= limit_s for f in viewer.frames) / max(1, len(viewer.frames))


def test_garbage_viewer_is_closed_others_unaffected(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            bad, *good = await connected_viewers(relay.port, cert, 3)
            for viewer in (bad, *good):
                await viewer.subscribed()
            streaming = asyncio.create_task(publisher.stream(90, fps=60, group_every=15, size=4000))
            await bad.until(lambda: len(bad.frames) >= 20)
            wt = bad.moq_link.wt
            garbage = wt.open_stream(False)
            wt.send(garbage, b"\x09\xff\x00garbage that is no moq-lite stream type")
            await bad.until(lambda: bad.moq_link.closed)
            assert bad.moq_link.closed_reason is not None
            assert bad.moq_link.closed_reason.startswith(
                f"closed by peer: {int(ErrorCode.PROTOCOL_VIOLATION)} "
            ), bad.moq_link.closed_reason
            await until(lambda: len(relay.links) == 3)  # publisher + the two good ones
            await streaming
            for viewer in good:
                await viewer.until_count(90)
                assert in_order(viewer, range(90))
                assert on_time(viewer) >= 0.95, sorted(f.latency for f in viewer.frames)[-5:]
            # Still accepting sessions, and serving them.
            newcomer = Viewer()
            await newcomer.connect(relay.port, cert)
            await newcomer.subscribed()
            await publisher.stream(15, fps=240, group_every=15)
            # The relay's cached latest group (75-89, finished) comes first, then live.
            await newcomer.until(lambda: in_order(newcomer, range(75, 105)))

    run(body())


# ---------------------------------------------------------------------------- 4


def test_viewers_leaving_mid_group_free_their_state(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            vanishing, resetting, steady = await connected_viewers(relay.port, cert, 3)
            for viewer in (vanishing, resetting, steady):
                await viewer.subscribed()
            gone_id, _ = relay_link(relay, vanishing)
            _, reset_link = relay_link(relay, resetting)
            streaming = asyncio.create_task(
                publisher.stream(80, fps=120, group_every=20, size=3000)
            )
            await steady.until(lambda: len(steady.frames) >= 25)  # group 1, mid-way
            vanishing.abort()  # CONNECTION_CLOSE, no WebTransport goodbye
            subscribe_stream = resetting.moq_link.moq._subscriptions[0].stream_id
            resetting.moq_link.wt.reset_stream(subscribe_stream, ErrorCode.CANCEL)
            resetting.moq_link.wt.stop_sending(subscribe_stream, ErrorCode.CANCEL)
            await until(lambda: relay.core.viewer_count("game", "video") == 1)
            await until(lambda: gone_id not in relay.links)
            assert relay.core.stats(gone_id) is None
            assert not reset_link.moq._requests and not reset_link.moq._out_groups
            await streaming
            await steady.until(lambda: len(steady.frames) == 80)
            assert in_order(steady, range(80))
            # The viewer that reset its subscription still has a working session.
            again = await resetting.subscribed()
            await publisher.stream(10, fps=240, group_every=10)
            # (after a replay of the relay's cached latest group: 60-79)
            await resetting.until(lambda: in_order(resetting, range(60, 90), again))
            assert publisher.subscribe_count == 1

    run(body())


# ---------------------------------------------------------------------------- 5


@pytest.mark.slow
def test_viewer_that_never_reads_is_bounded_and_skipped(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            slow, fast = await connected_viewers(relay.port, cert, 2)
            for viewer in (slow, fast):
                await viewer.subscribed()
            slow_id, slow_link = relay_link(relay, slow)
            resume = slow.stall()
            rng = random.Random(7)
            sizes = [rng.randrange(20_000, 60_000) for _ in range(150)]
            streaming = asyncio.create_task(
                publisher.stream(150, fps=30, group_every=30, size=lambda n: sizes[n])
            )
            peak_counted = peak_held = 0
            while not streaming.done():
                await asyncio.sleep(0.05)
                peak_counted = max(peak_counted, slow_link.wt.total_buffered())
                peak_held = max(peak_held, send_buffer_bytes(slow_link))
            await streaming
            await fast.until(lambda: len(fast.frames) == 150)
            stats = relay.core.stats(slow_id)
            assert stats is not None and stats.groups_skipped > 0
            # max_backlog_bytes (2 MB) plus a frame or so; 150 frames are ~6 MB. `held`
            # counts what aioquic keeps for streams the relay reset, too.
            assert peak_counted < 3_000_000, peak_counted
            assert peak_held < 3_000_000, peak_held
            assert in_order(fast, range(150))
            assert on_time(fast) >= 0.95, sorted(f.latency for f in fast.frames)[-10:]
            # It reads again: at the relay's next QUIC probe (the probe timeout doubled all
            # through the stall: 1-3 s later on a quiet machine, up to the stall's length on
            # a busy one) it follows again, from a group's start: one arrives whole.
            resume()
            streaming = asyncio.create_task(
                publisher.stream(450, fps=30, group_every=30, size=40_000)
            )

            def whole_new_group() -> bool:  # groups from 5 on came after the resume
                indexes: dict[int, list[int]] = {}
                for f in slow.frames:
                    indexes.setdefault(f.group, []).append(f.index)
                return any(g >= 5 and i == list(range(30)) for g, i in indexes.items())

            await slow.until(whole_new_group, timeout=15)
            streaming.cancel()
            assert groups_start_at_keyframes(slow)

    run(body(), timeout=45)


# ---------------------------------------------------------------------------- 6


def test_publisher_leaves_and_comes_back(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            viewer = Viewer()
            await viewer.connect(relay.port, cert)
            handle = viewer.request_announces("")

            def announces() -> list[bool]:
                return [
                    e.active
                    for e in viewer.of(ev.AnnounceReceived)
                    if e.handle == handle and e.path == "game"
                ]

            await viewer.until(lambda: announces() == [True])
            first = await viewer.subscribed()
            await publisher.stream(15, fps=240, group_every=10)
            await viewer.until(lambda: len(viewer.frames) == 15)
            publisher.abort()
            await viewer.until(lambda: announces() == [True, False])
            await viewer.until(lambda: viewer.closed_subscription(first) is not None)
            assert not relay.core.broadcasts and not relay.core._tracks
            publisher = await start_publisher(relay, cert)
            await viewer.until(lambda: announces() == [True, False, True])
            second = await viewer.subscribed()
            await publisher.stream(12, fps=240, group_every=10)
            await viewer.until(lambda: in_order(viewer, range(12), second))
            assert not viewer.moq_link.closed

    run(body())


# ---------------------------------------------------------------------------- 7


def test_missing_broadcast_and_track_are_refused_cleanly(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            viewer = Viewer()
            await viewer.connect(relay.port, cert)
            for broadcast, track in (("nothing", "video"), ("game", "nope")):
                sub = viewer.subscribe(broadcast, track)
                await viewer.until(partial(viewer.subscription_ended, sub))
                closed = viewer.closed_subscription(sub)
                assert closed == ev.SubscribeClosed(sub, ErrorCode.NOT_FOUND, False)
            assert not relay.core._tracks and not viewer.moq_link.closed
            sub = await viewer.subscribed()
            await publisher.stream(5, fps=240, group_every=10)
            await viewer.until(lambda: in_order(viewer, range(5), sub))

    run(body())


# ---------------------------------------------------------------------------- 8


def test_subscribe_storm_returns_to_baseline(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            steady, *churners = await connected_viewers(relay.port, cert, 6)
            churn_links = [relay_link(relay, v)[1] for v in churners]

            async def churn(viewer: Viewer, cycles: int, wait_frame: bool) -> None:
                for _ in range(cycles):
                    sub = viewer.subscribe()
                    if wait_frame:
                        await viewer.until(partial(viewer.got_frame, sub))
                    else:
                        await asyncio.sleep(0)
                    viewer.unsubscribe(sub)
                    await asyncio.sleep(0.005)

            async def storm() -> None:
                await asyncio.gather(
                    *(churn(v, 6, wait_frame=i % 2 == 0) for i, v in enumerate(churners))
                )

            # Phase 1: no steady viewer; every cycle may (un)subscribe upstream.
            streaming = asyncio.create_task(
                publisher.stream(400, fps=100, group_every=10, size=2000)
            )
            await storm()
            await until(lambda: not relay.core._tracks and not publisher.requests)
            # Phase 2: a steady viewer holds the track; the storm goes on around it.
            steady_sub = await steady.subscribed()
            baseline_subscribes = publisher.subscribe_count
            await storm()
            status, _ = await asyncio.wait_for(http_get("127.0.0.1", relay.port, "/stats"), 1)
            assert status == 200
            await until(lambda: relay.core.viewer_count("game", "video") == 1)
            assert publisher.subscribe_count == baseline_subscribes  # still one upstream
            streaming.cancel()
            publisher.end_group()
            for link in churn_links:
                assert not link.moq._requests and not link.moq._out_groups
                assert not link.moq.closed
            assert len(relay.core._tracks) == 1
            # Every frame from its first on (a group may still be in flight: wait for it).
            first = min(steady.numbers(steady_sub))
            sent = range(first, publisher.number)
            await steady.until(lambda: in_order(steady, sent, steady_sub))
            assert on_time(steady) >= 0.95
            steady.unsubscribe(steady_sub)
            await until(lambda: not relay.core._tracks and not publisher.requests)

    run(body(), timeout=30)


# ---------------------------------------------------------------------------- 9


def metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in metrics")


def test_metrics_and_stats_routes(cert: CertBundle) -> None:
    async def body() -> None:
        async with running_relay(cert) as relay:
            publisher = await start_publisher(relay, cert)
            first, second = await connected_viewers(relay.port, cert, 2)
            await first.subscribed()
            await publisher.stream(20, fps=240, group_every=10)
            await first.until(lambda: len(first.frames) == 20)
            status, body = await http_get("127.0.0.1", relay.port, "/stats")
            assert status == 200
            stats = json.loads(body)
            assert stats["sessions"] == 3 and stats["broadcasts"] == ["game"]
            assert stats["viewers"]["game/video"] == 1
            assert sum(s["frames_out"] for s in stats["per_session"].values()) == 20
            status, body = await http_get("::1", relay.port, "/metrics")
            assert status == 200
            text = body.decode()
            assert metric(text, "upcast_relay_frames_out_total") == 20
            assert metric(text, "upcast_relay_frames_in_total") == 20
            assert metric(text, "upcast_relay_connections") == 3
            # A viewer leaves while another one keeps counting: nothing is lost.
            await second.subscribed()
            await publisher.stream(10, fps=240, group_every=10)
            # 10-19 replayed from the relay's cache (latest group), then 20-29 live.
            await second.until(lambda: in_order(second, range(10, 30)))
            first.close()
            await until(lambda: len(relay.links) == 2)
            await publisher.stream(10, fps=240, group_every=10)
            await second.until(lambda: in_order(second, range(10, 40)))
            status, body = await http_get("127.0.0.1", relay.port, "/metrics")
            delivered = len(first.frames) + len(second.frames)
            assert metric(body.decode(), "upcast_relay_frames_out_total") == delivered
            assert metric(body.decode(), "upcast_relay_frames_in_total") == 40

    run(body())
