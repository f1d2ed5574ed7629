"""Load-test viewers: moq-lite sessions that watch a broadcast like the browser does.

Each viewer asks the relay for announces, and once the broadcast is announced
subscribes ``catalog.json``; the catalog names the video track, which it then
subscribes together with ``timing`` (the browser does the same, so the relay
sees the same requests). Frames are measured, never decoded: the load is the
relay's, not ours. Fragments are read with the general CMAF reader, so a stream
from another publisher (moq-rs's CMAF importer, FFmpeg) is measured too: its
init segment (the catalog's ``container.init``) gives the timescale and trex
defaults; without a timing track, loss and latency come from the media clock
(``viewer_stats``). Every viewer counts frames lost, groups skipped and freezes as the
browser does (``DeliveryCounters``); with ``feedback`` it also publishes its own
input broadcast and reports them to the session every 250 ms, as the page does
(``feedback_sender``), one viewer marked as the player if asked. ``run_viewers``
drives a group of viewers in one event loop along a RunPlan and reports progress
once a second.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import json
import logging
import resource
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from server.media.cmaf_read import TrackDefaults, parse_fragment, track_defaults, track_timescales
from server.moq.events import (
    AnnounceReceived,
    Event,
    FrameReceived,
    GroupClosed,
    GroupOpened,
    SessionError,
    SubscribeClosed,
)
from server.moq.session import SessionClosedError
from server.quic.client import WtConnectError
from server.quic.moq_link import MoqLink, connect_moq
from server.session.feedback import FEEDBACK_INTERVAL_MS

from .feedback_sender import FeedbackCounts, FeedbackSender
from .plan import RunPlan
from .viewer_stats import ViewerStats

log = logging.getLogger(__name__)

STALLED_S = 1.0  # no video frame for this long: ask for a keyframe (with feedback on)

CATALOG_TRACK = "catalog.json"
TIMING_TRACK = "timing"
PROGRESS_INTERVAL_S = 1.0
RECEIVE_BUFFER_BYTES = 4 << 20


@dataclass(frozen=True)
class ViewerConfig:
    relay_url: str
    broadcast: str
    cert_hash_hex: str | None
    connect_timeout_s: float
    token: str | None = None
    # Publish <broadcast>/input/<id> and send feedback every 250 ms (the token must
    # allow publishing there, as the player's does); ``player``: viewer 0 is the player.
    feedback: bool = False
    player: bool = False
    # Which video rendition of the catalog to watch: "first" (the player's track, as the
    # player's page), "smallest" (the lowest rung of a rendition ladder), or a track name.
    rendition: str = "first"


@dataclass(frozen=True)
class Snapshot:
    """One process's viewers at one moment (sent to the progress display)."""

    worker: int
    at: float  # time.monotonic()
    connected: int
    failed: int
    frames: tuple[int, ...]  # every video frame so far, per viewer (fps from deltas)
    bytes_total: int
    new_latency_ms: tuple[float, ...]  # publish -> receive samples since the last snapshot


@dataclass
class WorkerResult:
    worker: int
    stats: list[ViewerStats]
    cpu_s: float | None  # this process's CPU (user + system) inside the window
    window_wall_s: float


class LoadViewer:
    def __init__(self, index: int, config: ViewerConfig, window: tuple[float, float]) -> None:
        self.config = config
        self.stats = ViewerStats(index, window=window)
        self.link: MoqLink | None = None
        self._tracks: dict[int, str] = {}  # our subscription id -> track name
        self._video_track: str | None = None
        # From the catalog's init segment; upcast's own stream counts in microseconds.
        self._defaults: dict[int, TrackDefaults] = {}
        self._timescale = 1_000_000
        self._closing = False
        self.feedback: FeedbackSender | None = None
        if config.feedback:
            self.feedback = FeedbackSender(config.broadcast, player=config.player and index == 0)

    async def connect(self) -> None:
        self.stats.connect_started_s = start = time.monotonic()
        try:
            link = await connect_moq(
                self.config.relay_url,
                on_events=self._on_events,
                on_closed=self._on_closed,
                cert_hash_hex=self.config.cert_hash_hex,
                timeout=self.config.connect_timeout_s,
                token=self.config.token,
            )
        except (WtConnectError, ConnectionError, OSError, TimeoutError, ValueError) as exc:
            self.stats.error = f"connect: {exc}"
            return
        self.link = link
        _raise_receive_buffer(link)
        self.stats.connected = True
        self.stats.connect_ms = (time.monotonic() - start) * 1000.0
        if self._closing:
            self.close()
            return
        try:
            if self.feedback is not None:
                self.feedback.publish(link.moq)
            link.moq.request_announces("")
        except SessionClosedError:
            return
        link.flush()

    def close(self) -> None:
        self._closing = True
        link = self.link
        if link is not None and not link.closed:
            # The WebTransport close is all moq-lite has for ending a session; going
            # through MoqLink.close would log each of N normal closes as a warning.
            link.wt.close(0, "load test over")
        self.stats.drop_pending()

    def send_feedback(self) -> None:
        """One feedback message (if this viewer reports and the session subscribed)."""
        link, sender = self.link, self.feedback
        if link is None or sender is None or link.closed:
            return
        d = self.stats.delivery
        counts = FeedbackCounts(
            bytes=self.stats.bytes_total,
            lost=d.lost,
            skipped=d.skipped,
            freezes=d.freezes,
            freeze_ms=d.freeze_ms,
        )
        last = d.last_arrival_s
        stalled = last is not None and time.monotonic() - last > STALLED_S
        if sender.send(link.moq, counts, stalled=stalled):
            link.flush()

    # -- events --------------------------------------------------------------------

    def _on_closed(self, link: MoqLink, reason: str) -> None:
        if not self._closing:
            self.stats.disconnected = True
            self.stats.error = self.stats.error or f"disconnected: {reason}"

    def _on_events(self, link: MoqLink, events: list[Event]) -> None:
        if self.feedback is not None:
            self.feedback.on_events(link.moq, events)
        for event in events:
            if isinstance(event, FrameReceived):
                self._on_frame(link, event)
            elif isinstance(event, GroupOpened):
                track = self._tracks.get(event.subscription_id)
                if track is not None and track == self._video_track:
                    self.stats.on_group(time.monotonic(), event.sequence)
            elif isinstance(event, GroupClosed):
                track = self._tracks.get(event.subscription_id)
                if not event.complete and track is not None and track == self._video_track:
                    self.stats.on_group_reset(time.monotonic())
            elif isinstance(event, AnnounceReceived):
                if event.path.strip("/") == self.config.broadcast.strip("/") and event.active:
                    self._subscribe(link, CATALOG_TRACK)
            elif isinstance(event, SubscribeClosed):
                # Publisher gone (or refused): subscribe again on the next announce.
                track = self._tracks.pop(event.subscription_id, None)
                if track == CATALOG_TRACK:
                    self._video_track = None
            elif isinstance(event, SessionError):
                self.stats.error = f"protocol error: {event.reason}"

    def _subscribe(self, link: MoqLink, track: str) -> None:
        if track in self._tracks.values() or link.moq.closed:
            return
        subscription = link.moq.subscribe(self.config.broadcast, track)
        self._tracks[subscription] = track

    def _unsubscribe(self, link: MoqLink, track: str) -> None:
        for subscription, name in list(self._tracks.items()):
            if name == track:
                del self._tracks[subscription]
                if not link.moq.closed:
                    link.moq.unsubscribe(subscription)

    def _on_frame(self, link: MoqLink, event: FrameReceived) -> None:
        track = self._tracks.get(event.subscription_id)
        if track is None:
            return
        now = time.monotonic()
        if track == self._video_track:
            wall_us = time.time_ns() // 1000
            pts: int | None = None
            duration: int | None = None
            sequence: int | None = None
            try:
                info = parse_fragment(event.payload, self._defaults)
                pts = info.decode_time * 1_000_000 // self._timescale
                duration = sum(s.duration for s in info.samples) * 1_000_000 // self._timescale
                sequence = info.sequence
            except (ValueError, struct.error):
                self.stats.bad_fragments += 1
            self.stats.on_video(
                pts, len(event.payload), now, wall_us, duration_us=duration, sequence=sequence
            )
            if self.feedback is not None and pts is not None:
                self.feedback.note_frame(pts, now * 1000.0)
        elif track == TIMING_TRACK:
            try:
                record = json.loads(event.payload)
            except ValueError:
                return
            if isinstance(record, dict):
                self.stats.on_timing(record, now)
        elif track == CATALOG_TRACK:
            self._on_catalog(link, event.payload)

    def _on_catalog(self, link: MoqLink, payload: bytes) -> None:
        try:
            renditions = json.loads(payload)["video"]["renditions"]
            video_track = choose_rendition(renditions, self.config.rendition)
        except (ValueError, KeyError, TypeError, StopIteration):
            self.stats.error = "catalog without a video rendition"
            return
        if video_track is None:
            self.stats.error = f"catalog has no rendition {self.config.rendition!r}"
            return
        self.stats.catalog = True
        if self._video_track is None:
            self._read_init(renditions[video_track])
            self._video_track = str(video_track)
            self._subscribe(link, self._video_track)
            self._subscribe(link, TIMING_TRACK)
        elif str(video_track) != self._video_track:
            # The encoded size changed: the video moved to a new track (server/media/
            # catalog.py video_track_name). Leave the old one, follow the new one.
            self._unsubscribe(link, self._video_track)
            self.stats.on_new_track()
            self._read_init(renditions[video_track])
            self._video_track = str(video_track)
            self._subscribe(link, self._video_track)

    def _read_init(self, rendition: object) -> None:
        """Timescale and trex defaults of the video track's init segment, where given."""
        try:
            init = base64.b64decode(rendition["container"]["init"])  # type: ignore[index]
            defaults, timescales = track_defaults(init), track_timescales(init)
        except (KeyError, TypeError, ValueError, binascii.Error, struct.error):
            return
        self._defaults = defaults
        timescale = next(iter(timescales.values()), 0)
        if timescale > 0:
            self._timescale = timescale


def choose_rendition(renditions: dict[str, Any], wanted: str) -> str | None:
    """The track of the rendition ``wanted`` names ("first", "smallest" by coded pixels,
    or a track name), None when the catalog has no such track. StopIteration: none."""
    if wanted == "first":
        return str(next(iter(renditions)))
    if wanted == "smallest":

        def pixels(track: str) -> int:
            entry = renditions[track]
            size = entry.get("codedWidth", 0) * entry.get("codedHeight", 0)
            return size if isinstance(size, int) and size > 0 else 1 << 62

        return min(map(str, renditions), key=pixels)
    return wanted if wanted in renditions else None


def _raise_receive_buffer(link: MoqLink) -> None:
    """A real viewer has a machine to itself; here one process drains many sockets, and
    a burst (one frame to every viewer at once) must not overflow the kernel's default
    ~208 KiB: a dropped datagram costs a QUIC loss recovery, which the report would
    blame on the relay. Linux caps the value at net.core.rmem_max."""
    transport = link.wt.conn._transport
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)


def raise_fd_limit(viewers: int) -> None:
    """Each viewer has its own UDP socket: 1000 of them pass the usual soft limit of 1024."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = viewers + 256
    if soft != resource.RLIM_INFINITY and soft < want:
        new_soft = want if hard == resource.RLIM_INFINITY else min(want, hard)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (new_soft, hard))


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def _sleep_until(deadline: float) -> None:
    delay = deadline - time.monotonic()
    if delay > 0:
        await asyncio.sleep(delay)


class _Reporter:
    """Builds the once-a-second Snapshot; hands out only latency samples not yet sent."""

    def __init__(self, worker: int, viewers: Sequence[LoadViewer]) -> None:
        self.worker = worker
        self.viewers = viewers
        self._sent = [0] * len(viewers)

    def snapshot(self) -> Snapshot:
        new: list[float] = []
        for i, viewer in enumerate(self.viewers):
            samples = viewer.stats.publish_to_receive_ms
            new.extend(samples[self._sent[i] :])
            self._sent[i] = len(samples)
        stats = [v.stats for v in self.viewers]
        return Snapshot(
            worker=self.worker,
            at=time.monotonic(),
            connected=sum(1 for s in stats if s.connected and not s.disconnected),
            failed=sum(1 for s in stats if s.error is not None),
            frames=tuple(s.received_total for s in stats),
            bytes_total=sum(s.bytes_total for s in stats),
            new_latency_ms=tuple(new),
        )


async def run_viewers(
    config: ViewerConfig,
    plan: RunPlan,
    indices: Sequence[int],
    sink: Callable[[Snapshot], None],
    *,
    worker: int = 0,
) -> WorkerResult:
    """Connect viewers ``indices`` on the plan's ramp, measure, close them at ``plan.stop``."""
    raise_fd_limit(len(indices))
    viewers = [LoadViewer(i, config, plan.window) for i in indices]

    async def connect_later(viewer: LoadViewer, at: float) -> None:
        await _sleep_until(at)
        await viewer.connect()

    connects = [
        asyncio.create_task(connect_later(v, plan.connect_at(i)))
        for v, i in zip(viewers, indices, strict=True)
    ]
    reporter = _Reporter(worker, viewers)

    async def report_loop() -> None:
        while True:
            await asyncio.sleep(PROGRESS_INTERVAL_S)
            sink(reporter.snapshot())

    async def feedback_loop() -> None:
        while True:
            await asyncio.sleep(FEEDBACK_INTERVAL_MS / 1000.0)
            for viewer in viewers:
                viewer.send_feedback()

    reporting = asyncio.create_task(report_loop())
    feedback = asyncio.create_task(feedback_loop()) if config.feedback else None
    try:
        await _sleep_until(plan.window_start)
        cpu_start, wall_start = _cpu_seconds(), time.monotonic()
        await _sleep_until(plan.window_end)
        cpu_s, wall_s = _cpu_seconds() - cpu_start, time.monotonic() - wall_start
        await _sleep_until(plan.stop)
    finally:
        reporting.cancel()
        if feedback is not None:
            feedback.cancel()
        for viewer, task in zip(viewers, connects, strict=True):
            if not task.done():
                task.cancel()
                viewer.stats.error = viewer.stats.error or "connect did not finish in time"
        loops = [reporting] if feedback is None else [reporting, feedback]
        await asyncio.gather(*connects, *loops, return_exceptions=True)
        for viewer in viewers:
            viewer.close()
    sink(reporter.snapshot())
    await asyncio.sleep(0.05)  # let the CONNECTION_CLOSE datagrams leave
    return WorkerResult(worker, [v.stats for v in viewers], cpu_s, wall_s)
