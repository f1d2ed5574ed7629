"""GameBroadcast: one game session's broadcast on a moq-lite session.

It publishes three tracks and listens for viewers' inputs:

- ``catalog.json``: the hang catalog (codec, size, the CMAF init segment); each
  subscriber gets one group holding the whole JSON.
- ``video``: one CMAF fragment (moof+mdat) per frame, a new group at each
  keyframe, so any group is decodable from its first frame. When the encoded size
  changes, the video moves to a new track (``video.1``, ``video.2``...) named by a new
  catalog (:meth:`GameBroadcast.switch_video`).
- ``timing``: one JSON record per video frame, in groups numbered like the
  video's (see timing_track.py); with audio on, also one ``"kind": "audio"`` record
  per audio packet (its stage stamps) in the same groups.
- ``audio`` (when the session has sound): one hang ``legacy`` frame (varint pts in
  microseconds + an Opus packet) per 10 ms, a new group every ``AUDIO_GROUP_FRAMES``
  packets or when the pts jumps, so a late joiner starts within a tenth of a second.
- ``video.<W>x<H>`` (with a rendition ladder, server/media/ladder.py): the spectator
  rungs, one CMAF fragment per frame, a new group at each rung IDR (every second and at
  the player's track's IDRs), listed after the player's track in the catalog. A new
  subscriber of a rung asks the ladder (not the player's encoder) for a keyframe.
- ``status``: the session's state and the result of the last control request
  (server/session/session_control.py), one JSON frame per group and a new
  group per change, so a subscriber gets the current state at once.
- inputs: viewers publish ``<name>/input/<id>`` broadcasts with an ``input``
  track; we ask the peer (the relay) for announces under ``<name>/input`` and
  subscribe to each one.

The object drives a MoqSession and does no I/O, so it is tested over the
in-memory pipe like the protocol code. A subscriber that arrives mid-group
(the relay's first subscription) makes us ask the encoder for a keyframe and
gets data from the next group on: a group never starts without its keyframe.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from server.frames.frame import FrameMeta
from server.frames.timing import Stage, stamp
from server.media.audio_encode import legacy_frame
from server.media.catalog import AUDIO_TRACK
from server.media.encode import EncodedFrame
from server.moq import paths
from server.moq.errors import ErrorCode
from server.moq.events import (
    AnnounceReceived,
    AnnouncesEnded,
    Event,
    FrameReceived,
    GroupCancelled,
    SubscribeCancelled,
    SubscribeClosed,
    SubscribeRequested,
)
from server.moq.session import MoqSession
from server.session.audio_capture import CapturedAudio
from server.session.session_control import STATUS_TRACK
from server.session.timing_track import TRACK_NAME as TIMING_TRACK
from server.session.timing_track import audio_timing_record, encode_timing, timing_record

log = logging.getLogger(__name__)

CATALOG_TRACK = "catalog.json"
VIDEO_TRACK = "video"
INPUT_TRACK = "input"
TRACKS = (CATALOG_TRACK, VIDEO_TRACK, TIMING_TRACK, STATUS_TRACK, AUDIO_TRACK)
# A broadcast without sound refuses ``audio`` like any unknown track.
SILENT_TRACKS = (CATALOG_TRACK, VIDEO_TRACK, TIMING_TRACK, STATUS_TRACK)
AUDIO_GROUP_FRAMES = 10  # 100 ms of Opus per group: what a joining viewer may wait for
INPUT_MAX_LATENCY_MS = 60_000
MAX_INPUT_BROADCASTS = 64  # viewers sending input at once; more are ignored (and logged)


@dataclass
class _Subscriber:
    track: str
    group_stream: int | None = None  # the open group stream, None until the next group


@dataclass
class BroadcastStats:
    frames_published: int = 0
    groups: int = 0
    audio_packets: int = 0
    audio_groups: int = 0
    input_frames: int = 0
    input_broadcasts: int = 0
    subscribers: dict[str, int] = field(default_factory=dict)


class GameBroadcast:
    def __init__(
        self,
        name: str,
        catalog_json: bytes,
        *,
        on_input: Callable[[str, bytes], None],
        on_keyframe_wanted: Callable[[], None],
        on_input_ended: Callable[[str], None] | None = None,
        audio: bool = False,
        rung_tracks: tuple[str, ...] = (),
        on_rung_keyframe_wanted: Callable[[], None] | None = None,
        on_rungs_watched: Callable[[frozenset[str]], None] | None = None,
    ) -> None:
        """``on_input_ended(source)``: a viewer's input broadcast ended (it left).
        ``rung_tracks``: the rendition ladder's tracks; ``on_rung_keyframe_wanted``: a
        subscriber of one of them waits for the ladder's next IDR;
        ``on_rungs_watched(tracks)``: the rungs with a subscriber changed."""
        self.name = paths.normalize(name)
        self._static_tracks = TRACKS if audio else SILENT_TRACKS
        # The video track of the size encoded now: ``video`` until the first size change
        # (switch_video), then ``video.1``... A subscriber of an older one keeps its
        # subscription (it follows the catalog and closes it) but gets no more groups.
        self.video_track = VIDEO_TRACK
        self.catalog_json = catalog_json
        self.input_prefix = paths.join(self.name, "input")
        self.stats = BroadcastStats()
        self._on_input = on_input
        self._on_keyframe_wanted = on_keyframe_wanted
        self._on_input_ended = on_input_ended
        self.rung_tracks = rung_tracks
        self._on_rung_keyframe_wanted = on_rung_keyframe_wanted
        self._rung_seq: dict[str, int] = dict.fromkeys(rung_tracks, -1)
        self._on_rungs_watched = on_rungs_watched
        self._rungs_watched: frozenset[str] = frozenset()
        self._session: MoqSession | None = None
        self._subscribers: dict[int, _Subscriber] = {}  # request id -> state
        self._input_interest: int | None = None
        self._inputs: dict[int, str] = {}  # our subscription id -> input broadcast path
        self._input_paths: dict[str, int] = {}
        self._group_seq = -1  # sequence of the current video/timing group
        self._catalog_seq = 0
        self.status_json: bytes | None = None  # None until the session says something
        self._status_seq = -1
        self._published = 0  # frames published: the timing records' ``n``
        self._audio_seq = -1
        self._audio_in_group = AUDIO_GROUP_FRAMES  # the first packet opens a group
        # What the stream runs now (upscaler, scale), sent in every timing record so a
        # page that joins later shows the server's settings, not its own defaults.
        self.stream_state: dict[str, str | float | bool] = {}

    @property
    def tracks(self) -> tuple[str, ...]:
        """The tracks a subscriber may ask for now."""
        static: tuple[str, ...] = self._static_tracks
        if self.video_track != VIDEO_TRACK:
            static = tuple(self.video_track if t == VIDEO_TRACK else t for t in static)
        return static + self.rung_tracks

    # -- session lifecycle ------------------------------------------------------------

    def attach(self, session: MoqSession) -> None:
        """Publish on a (new) session, e.g. after reconnecting to the relay."""
        self._session = session
        self._subscribers.clear()
        self._inputs.clear()
        self._input_paths.clear()
        session.publish(self.name)
        self._input_interest = session.request_announces(self.input_prefix)
        self._count_subscribers()

    def detach(self) -> None:
        self._session = None
        self._subscribers.clear()
        self._inputs.clear()
        self._input_paths.clear()
        self._count_subscribers()

    # -- events from the session ---------------------------------------------------------

    def handle(self, events: list[Event]) -> None:
        for event in events:
            if isinstance(event, SubscribeRequested):
                self._on_subscribe(event)
            elif isinstance(event, SubscribeCancelled):
                self._subscribers.pop(event.request_id, None)
            elif isinstance(event, GroupCancelled):
                sub = self._subscribers.get(event.request_id)
                if sub is not None and sub.group_stream == event.stream_id:
                    sub.group_stream = None  # the peer skipped this group: resume at the next
            elif isinstance(event, AnnounceReceived) and event.handle == self._input_interest:
                self._on_input_announce(event)
            elif isinstance(event, AnnouncesEnded) and event.handle == self._input_interest:
                self._input_interest = None
            elif isinstance(event, FrameReceived) and event.subscription_id in self._inputs:
                self.stats.input_frames += 1
                self._on_input(self._inputs[event.subscription_id], event.payload)
            elif isinstance(event, SubscribeClosed) and event.subscription_id in self._inputs:
                path = self._inputs.pop(event.subscription_id)
                self._input_paths.pop(path, None)
        self._count_subscribers()

    def _on_subscribe(self, e: SubscribeRequested) -> None:
        session = self._session
        assert session is not None
        if paths.normalize(e.broadcast) != self.name or e.track not in self.tracks:
            log.info("refusing subscribe to %s/%s: no such track", e.broadcast, e.track)
            session.reject_subscribe(e.request_id, ErrorCode.NOT_FOUND)
            return
        if not session.accept_subscribe(e.request_id):
            return
        sub = _Subscriber(e.track)
        self._subscribers[e.request_id] = sub
        log.info("subscriber %d for track %s", e.request_id, e.track)
        if e.track == CATALOG_TRACK:
            self._send_catalog(e.request_id, sub)
        elif e.track == STATUS_TRACK:
            self._send_status(e.request_id)
        elif e.track == AUDIO_TRACK:
            pass  # every audio group starts clean: the subscriber joins at the next one
        elif e.track in self.rung_tracks:
            if self._on_rung_keyframe_wanted is not None:
                self._on_rung_keyframe_wanted()
        else:
            self._on_keyframe_wanted()

    def _send_catalog(self, request_id: int, sub: _Subscriber) -> None:
        session = self._session
        assert session is not None
        stream = session.open_group(request_id, self._catalog_seq)
        if stream is None:
            return
        session.write_frame(stream, self.catalog_json)
        session.finish_group(stream)

    def set_catalog(self, catalog_json: bytes) -> None:
        """A new catalog (size or codec changed): a new group for every subscriber."""
        self.catalog_json = catalog_json
        self._catalog_seq += 1
        for request_id, sub in list(self._subscribers.items()):
            if sub.track == CATALOG_TRACK:
                self._send_catalog(request_id, sub)

    def switch_video(self, track: str, catalog_json: bytes) -> None:
        """The encoded size changed: publish from now on on ``track``, described by
        ``catalog_json`` (sent to every catalog subscriber at once). Call it before
        publishing the new size's first frame (an IDR), which opens the new track's
        first group. The old track's open groups end here, complete."""
        if track == self.video_track:
            return
        session = self._session
        for sub in self._subscribers.values():
            if sub.track == self.video_track and sub.group_stream is not None:
                if session is not None and not session.closed:
                    session.finish_group(sub.group_stream)
                sub.group_stream = None
        log.info("video now on track %s", track)
        self.video_track = track
        self.set_catalog(catalog_json)

    def set_status(self, status_json: bytes) -> None:
        """A new status record: a new group for every status subscriber."""
        self.status_json = status_json
        self._status_seq += 1
        for request_id, sub in list(self._subscribers.items()):
            if sub.track == STATUS_TRACK:
                self._send_status(request_id)

    def _send_status(self, request_id: int) -> None:
        session = self._session
        if session is None or self.status_json is None:
            return
        stream = session.open_group(request_id, self._status_seq)
        if stream is None:
            return
        session.write_frame(stream, self.status_json)
        session.finish_group(stream)

    def _on_input_announce(self, e: AnnounceReceived) -> None:
        session = self._session
        assert session is not None
        path = paths.normalize(e.path)
        if paths.strip_prefix(self.input_prefix, path) in (None, ""):
            return
        if e.active and path not in self._input_paths:
            if len(self._input_paths) >= MAX_INPUT_BROADCASTS:
                log.warning("ignoring input broadcast %s: %d already", path, len(self._input_paths))
                return
            # A long max latency: a relay skips a lagging subscriber's current group,
            # and a page sends all its input in one long group, so a skip (the
            # session's loop stalled half a second on a loaded machine) would lose
            # every later input and feedback message from that viewer. Input is tiny;
            # late is better than never.
            subscription = session.subscribe(
                path, INPUT_TRACK, priority=255, max_latency_ms=INPUT_MAX_LATENCY_MS
            )
            self._inputs[subscription] = path
            self._input_paths[path] = subscription
            self.stats.input_broadcasts += 1
            log.info("viewer input from %s", path)
        elif not e.active and path in self._input_paths:
            subscription = self._input_paths.pop(path)
            self._inputs.pop(subscription, None)
            session.unsubscribe(subscription)
            log.info("viewer input from %s ended", path)
            if self._on_input_ended is not None:
                self._on_input_ended(path)

    def _count_subscribers(self) -> None:
        counts = dict.fromkeys(self.tracks, 0)
        for sub in self._subscribers.values():
            counts[sub.track] = counts.get(sub.track, 0) + 1  # an old video track too
        self.stats.subscribers = counts
        watched = frozenset(t for t in self.rung_tracks if counts.get(t, 0) > 0)
        if watched != self._rungs_watched:
            self._rungs_watched = watched
            if self._on_rungs_watched is not None:
                self._on_rungs_watched(watched)

    # -- media ---------------------------------------------------------------------------

    def publish_frame(self, encoded: EncodedFrame, meta: FrameMeta) -> None:
        """Put one encoded frame and its timing record on every subscriber's group.

        Stamps ``publish`` on ``meta`` right before the fragment goes to QUIC."""
        if encoded.keyframe:
            self._group_seq += 1
            self.stats.groups += 1
        session = self._session
        n = self._published
        self._published += 1
        self.stats.frames_published += 1
        if session is None or session.closed:
            return
        video = [(r, s) for r, s in self._subscribers.items() if s.track == self.video_track]
        timing = [(r, s) for r, s in self._subscribers.items() if s.track == TIMING_TRACK]
        self._advance_groups(session, video + timing, encoded.keyframe)
        stamp(meta.stamps, Stage.PUBLISH)
        for _, sub in video:
            if sub.group_stream is not None:
                session.write_frame(sub.group_stream, encoded.fragment)
        if timing:
            record = timing_record(meta, n=n, pts_us=encoded.pts_us, keyframe=encoded.keyframe)
            record.update(self.stream_state)
            payload = encode_timing(record)
            for _, sub in timing:
                if sub.group_stream is not None:
                    session.write_frame(sub.group_stream, payload)

    def _advance_groups(
        self, session: MoqSession, subs: list[tuple[int, _Subscriber]], keyframe: bool
    ) -> None:
        if not keyframe or self._group_seq < 0:
            return
        for request_id, sub in subs:
            if sub.group_stream is not None:
                session.finish_group(sub.group_stream)
            sub.group_stream = session.open_group(request_id, self._group_seq)

    def publish_rung(self, track: str, encoded: EncodedFrame) -> None:
        """Put one frame of a ladder rung on its subscribers' group (a new group at
        each IDR; a subscriber that came mid-group starts at the next one)."""
        if track not in self._rung_seq:
            return  # a rung dropped meanwhile
        if encoded.keyframe:
            self._rung_seq[track] += 1
        session = self._session
        if session is None or session.closed:
            return
        subs = [(r, s) for r, s in self._subscribers.items() if s.track == track]
        if encoded.keyframe:
            for request_id, sub in subs:
                if sub.group_stream is not None:
                    session.finish_group(sub.group_stream)
                sub.group_stream = session.open_group(request_id, self._rung_seq[track])
        for _, sub in subs:
            if sub.group_stream is not None:
                session.write_frame(sub.group_stream, encoded.fragment)

    def drop_rung(self, track: str, catalog_json: bytes) -> None:
        """A rung's encoder failed: end its subscriptions and publish ``catalog_json``
        (the catalog without it); the other tracks go on."""
        if track not in self._rung_seq:
            return
        del self._rung_seq[track]
        self.rung_tracks = tuple(t for t in self.rung_tracks if t != track)
        session = self._session
        for request_id, sub in list(self._subscribers.items()):
            if sub.track != track:
                continue
            del self._subscribers[request_id]
            if session is not None and not session.closed:
                if sub.group_stream is not None:
                    session.finish_group(sub.group_stream)
                session.end_subscription(request_id)
        self._count_subscribers()
        self.set_catalog(catalog_json)

    def publish_audio(self, captured: CapturedAudio) -> None:
        """Put one Opus packet on the audio subscribers' group and its stamps on timing."""
        new_group = captured.discontinuity or self._audio_in_group >= AUDIO_GROUP_FRAMES
        if new_group:
            self._audio_seq += 1
            self._audio_in_group = 0
            self.stats.audio_groups += 1
        self._audio_in_group += 1
        self.stats.audio_packets += 1
        session = self._session
        if session is None or session.closed:
            return
        audio = [(r, s) for r, s in self._subscribers.items() if s.track == AUDIO_TRACK]
        if new_group:
            for request_id, sub in audio:
                if sub.group_stream is not None:
                    session.finish_group(sub.group_stream)
                sub.group_stream = session.open_group(request_id, self._audio_seq)
        publish_us = time.time_ns() // 1000
        frame = legacy_frame(captured.packet)
        for _, sub in audio:
            if sub.group_stream is not None:
                session.write_frame(sub.group_stream, frame)
        timing = [s for s in self._subscribers.values() if s.track == TIMING_TRACK]
        if timing:
            payload = encode_timing(audio_timing_record(captured, publish_us=publish_us))
            for sub in timing:
                if sub.group_stream is not None:
                    session.write_frame(sub.group_stream, payload)
