"""Transport-agnostic moq-lite relay: learns broadcasts, fans groups out, skips slow viewers.

The adapter owns the MoqSessions (it knows how to open streams); the core reacts to their
events and drives them with commands. After feeding a session, the adapter calls
`handle(conn_id)` and then flushes `take_transmit()` of every connection id returned (the
core writes to *other* sessions: viewers of a publisher's frames). `poll()` is called on a
timer for the slow-viewer check.

Choices (and why):
- ONE upstream subscription per (broadcast, track), shared by all viewers; dropped when the
  last viewer leaves, so a publisher only sends what someone watches.
- The latest group's frames are cached (bounded by `max_group_cache_bytes`) so a new viewer
  starts at once from that group's first frame (a keyframe), then continues live.
- A viewer whose backlog passes `max_backlog_bytes`, or whose oldest unsent frame is older
  than its max latency, gets its current group reset (ErrorCode.SKIPPED) and joins the next
  group at its start: frames inside a group depend on its keyframe, so a group is the
  smallest unit that can be skipped. The backlog counts the current group's stream plus the
  finished groups of that subscription not yet sent ("tails"), whose frames also count for
  the max latency (short groups finish before they are old): a viewer that never reads
  would otherwise take a whole finished group per group, each under the limit, without
  bound. Nothing is buffered without bound. A viewer with no QUIC stream credit left
  (MAX_STREAMS: it stopped reading) misses each group that starts meanwhile the same way.
- A viewer that was skipped, or that joins where no group can be replayed, waits for the
  next group, which only a keyframe starts: with intra refresh that is the publisher's
  safety IDR, seconds away, and moq-lite has no message to ask for one. So the relay
  *nudges* the publisher: a second, short-lived SUBSCRIBE to the same track, cancelled
  as soon as it is accepted (its groups are ignored). A publisher that starts a new
  subscriber at a keyframe (ours does: server/session/broadcast.py) sends one to every
  subscriber, the relay's own included; any other sees one more subscriber come and go.
  At most one nudge per track per ``nudge_interval_s``, so a viewer skipped over and over
  cannot make the stream all keyframes.
- Publisher leaves: its broadcasts are announced inactive and viewer subscriptions are
  ended (FIN). Viewers re-subscribe when the broadcast is announced again. We do not keep
  viewers attached across publishers: a new publisher restarts group sequences, and an
  ordered @moq/lite consumer would silently drop the "older" groups.
- Broadcast owner: the latest announcer wins, so a publisher that reconnects before its old
  connection times out takes over at once.
- Access (a connection's `AccessPolicy`, from its token): announcing a path it may not
  publish closes that one session (moq-lite has no per-announce error, and a peer that
  tries is not one to keep talking to); subscribing to a path it may not read is refused
  (UNAUTHORIZED) on that request only; it is told only about broadcasts it may read.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Protocol

from .errors import ErrorCode
from .events import (
    AnnounceReceived,
    AnnouncesEnded,
    FrameReceived,
    GroupCancelled,
    GroupClosed,
    GroupOpened,
    SessionError,
    SubscribeAccepted,
    SubscribeCancelled,
    SubscribeClosed,
    SubscribeRequested,
    SubscribeUpdated,
)
from .session import MoqSession

ConnId = Hashable
TrackKey = tuple[str, str]  # (broadcast path, track name)
ViewerKey = tuple[ConnId, int]  # (viewer connection, its request id)


class AccessPolicy(Protocol):
    """What one connection may do (server.auth.Grant implements it)."""

    def may_publish(self, path: str) -> bool: ...

    def may_subscribe(self, path: str) -> bool: ...


class OpenAccess:
    """Everything allowed: connections added without a policy."""

    def may_publish(self, path: str) -> bool:
        return True

    def may_subscribe(self, path: str) -> bool:
        return True


OPEN_ACCESS = OpenAccess()
# Subscriptions refused over max_subscriptions_per_track before the session is closed.
MAX_REFUSED_SUBSCRIBES = 64

# on_denied(connection, "publish" | "subscribe", path): the adapter logs and counts.
DeniedHook = Callable[[ConnId, str, str], None]


@dataclass(slots=True)
class ConnStats:
    """Per-connection counters for metrics (payload bytes, not wire bytes)."""

    frames_in: int = 0
    bytes_in: int = 0
    frames_out: int = 0
    bytes_out: int = 0
    groups_skipped: int = 0
    subscribes_refused: int = 0  # over max_subscriptions_per_track
    keyframe_nudges: int = 0  # short-lived subscribes sent to this publisher (module doc)


@dataclass(slots=True)
class _Conn:
    session: MoqSession
    interest: int
    access: AccessPolicy
    stats: ConnStats = field(default_factory=ConnStats)
    broadcasts: set[str] = field(default_factory=set)
    upstream: dict[int, TrackKey] = field(default_factory=dict)  # our subscription id
    nudges: set[int] = field(default_factory=set)  # our keyframe-nudge subscription ids


@dataclass(slots=True)
class _Group:
    sequence: int
    frames: list[bytes] = field(default_factory=list)
    cached_bytes: int = 0
    cacheable: bool = True
    done: bool = False
    complete: bool = False


@dataclass(slots=True)
class _Out:
    """One viewer's copy of one group: a downstream uni stream."""

    stream_id: int
    written: int = 0
    marks: deque[tuple[int, float]] = field(default_factory=deque)  # (end offset, time)


@dataclass(slots=True)
class _Viewer:
    conn: ConnId
    request_id: int
    max_latency_s: float | None
    accepted: bool = False
    outs: dict[int, _Out] = field(default_factory=dict)  # upstream group stream -> out
    # Finished group streams whose bytes are not all delivered yet (stream id -> out).
    tails: dict[int, _Out] = field(default_factory=dict)
    start: int | None = None  # sequence of the first group it was given


@dataclass(slots=True)
class _Track:
    key: TrackKey
    publisher: ConnId
    subscription_id: int
    accepted: bool = False
    groups: dict[int, _Group] = field(default_factory=dict)  # upstream group stream -> group
    latest: int | None = None  # upstream stream of the newest group
    viewers: dict[ViewerKey, _Viewer] = field(default_factory=dict)
    nudged_at: float | None = None  # when the publisher was last nudged for a keyframe


class RelayCore:
    def __init__(
        self,
        buffered_bytes: Callable[[ConnId, int], int],
        *,
        clock: Callable[[], float] = time.monotonic,
        max_backlog_bytes: int = 2 * 1024 * 1024,
        default_max_latency_s: float | None = None,
        max_group_cache_bytes: int = 32 * 1024 * 1024,
        max_subscriptions_per_track: int = 2,
        nudge_interval_s: float = 1.0,
        on_frame: Callable[[TrackKey, int, float], None] | None = None,
        on_denied: DeniedHook | None = None,
    ) -> None:
        """``on_frame(track, payload bytes, seconds spent fanning it out)`` is called for
        every frame a publisher delivers: the relay's monitor and metrics.
        ``max_subscriptions_per_track``: concurrent subscriptions of one connection to
        one track (two lets a player overlap a re-subscribe); without it one session
        could make the relay send it every frame hundreds of times.
        ``nudge_interval_s``: the least time between two keyframe nudges of a track's
        publisher (see the module doc)."""
        self._buffered_bytes = buffered_bytes
        self._on_denied = on_denied
        self._on_frame_hook = on_frame
        self._clock = clock
        self.max_backlog_bytes = max_backlog_bytes
        self.default_max_latency_s = default_max_latency_s
        self.max_group_cache_bytes = max_group_cache_bytes
        self.max_subscriptions_per_track = max_subscriptions_per_track
        self.nudge_interval_s = nudge_interval_s
        self._conns: dict[ConnId, _Conn] = {}
        self._owners: dict[str, ConnId] = {}  # broadcast path -> publishing connection
        self._hops: dict[str, int] = {}
        self._tracks: dict[TrackKey, _Track] = {}
        self._touched: set[ConnId] = set()

    # ------------------------------------------------------------------ adapter API

    def add_connection(
        self, conn_id: ConnId, session: MoqSession, access: AccessPolicy = OPEN_ACCESS
    ) -> set[ConnId]:
        """Register a session: ask it for its broadcasts, offer it everyone else's (those
        its `access` lets it read)."""
        interest = session.request_announces("")
        self._conns[conn_id] = _Conn(session, interest, access)
        for path, owner in self._owners.items():
            if owner != conn_id and access.may_subscribe(path):
                session.publish(path, self._hops[path])
        self._touched.add(conn_id)
        return self._take_touched()

    def remove_connection(self, conn_id: ConnId) -> set[ConnId]:
        """The connection is gone (closed, timed out, protocol error). Idempotent."""
        conn = self._conns.pop(conn_id, None)
        if conn is not None:
            for path in list(conn.broadcasts):
                self._withdraw(path)
            for track in list(self._tracks.values()):
                if track.publisher == conn_id:
                    self._end_track(track, ErrorCode.GONE)
                    continue
                for key in [k for k in track.viewers if k[0] == conn_id]:
                    self._remove_viewer(track, key)
        self._touched.discard(conn_id)
        return self._take_touched()

    def handle(self, conn_id: ConnId) -> set[ConnId]:
        """Drain and act on the events of one session; returns connections to flush.

        The result always contains `conn_id` itself, even when a protocol error removed it:
        its CloseSession transmit still has to go out.
        """
        conn = self._conns.get(conn_id)
        if conn is not None:
            for event in conn.session.take_events():
                if conn_id not in self._conns:
                    break  # removed by an earlier event (session error)
                self._dispatch(conn_id, conn, event)
        touched = self._take_touched()
        touched.add(conn_id)
        return touched

    def poll(self) -> set[ConnId]:
        """Periodic slow-viewer check for viewers whose publisher is quiet."""
        now = self._clock()
        for track in list(self._tracks.values()):
            for viewer in list(track.viewers.values()):
                for upstream, out in list(viewer.outs.items()):
                    if self._lagging(viewer, out, now):
                        self._skip(viewer, upstream)
                        self._nudge(track, now)
                if self._check_tails(viewer, now) and not viewer.outs:
                    self._nudge(track, now)
        return self._take_touched()

    def stats(self, conn_id: ConnId) -> ConnStats | None:
        conn = self._conns.get(conn_id)
        return None if conn is None else conn.stats

    @property
    def broadcasts(self) -> dict[str, ConnId]:
        return dict(self._owners)

    def viewer_counts(self) -> dict[TrackKey, int]:
        """Subscribers of every track the relay carries now."""
        return {key: len(track.viewers) for key, track in self._tracks.items()}

    def viewer_count(self, broadcast: str, track: str) -> int:
        found = self._tracks.get((broadcast, track))
        return 0 if found is None else len(found.viewers)

    # -------------------------------------------------------------------- dispatch

    def _dispatch(self, conn_id: ConnId, conn: _Conn, event: object) -> None:
        if isinstance(event, FrameReceived):
            self._on_frame(conn, event)
        elif isinstance(event, GroupOpened):
            self._on_group_opened(conn, event)
        elif isinstance(event, GroupClosed):
            self._on_group_closed(conn, event)
        elif isinstance(event, AnnounceReceived):
            if event.handle == conn.interest:
                self._on_announce(conn_id, event)
        elif isinstance(event, AnnouncesEnded):
            if event.handle == conn.interest:
                for path in list(conn.broadcasts):
                    self._withdraw(path)
        elif isinstance(event, SubscribeRequested):
            self._on_viewer_subscribe(conn_id, conn, event)
        elif isinstance(event, SubscribeCancelled):
            self._on_viewer_cancel(conn_id, event.request_id)
        elif isinstance(event, SubscribeUpdated):
            viewer = self._find_viewer(conn_id, event.request_id)
            if viewer is not None:
                viewer.max_latency_s = self._latency(event.max_latency_ms)
        elif isinstance(event, GroupCancelled):
            viewer = self._find_viewer(conn_id, event.request_id)
            if viewer is not None:
                viewer.tails.pop(event.stream_id, None)
                for upstream, out in list(viewer.outs.items()):
                    if out.stream_id == event.stream_id:
                        del viewer.outs[upstream]
        elif isinstance(event, SubscribeAccepted) and event.subscription_id in conn.nudges:
            # The publisher has seen a new subscriber (and made its keyframe): done.
            conn.nudges.discard(event.subscription_id)
            conn.session.unsubscribe(event.subscription_id)
        elif isinstance(event, SubscribeClosed) and event.subscription_id in conn.nudges:
            conn.nudges.discard(event.subscription_id)
        elif isinstance(event, SubscribeAccepted):
            track = self._upstream_track(conn, event.subscription_id)
            if track is not None:
                track.accepted = True
                for viewer in list(track.viewers.values()):
                    self._start_viewer(track, viewer)
        elif isinstance(event, SubscribeClosed):
            track = self._upstream_track(conn, event.subscription_id)
            if track is not None:
                code = ErrorCode.NOT_FOUND if not event.accepted else ErrorCode.GONE
                self._end_track(track, code)
        elif isinstance(event, SessionError):
            self.remove_connection(conn_id)
        # AnnounceInterestReceived: the session answers from its published set.
        # SubscribeDropped, GoawayReceived: nothing to do for a relay.

    # ----------------------------------------------------------------- announces

    def _on_announce(self, conn_id: ConnId, event: AnnounceReceived) -> None:
        path = event.path
        owner = self._owners.get(path)
        if not event.active:
            if owner == conn_id:
                self._withdraw(path)
            return
        if owner == conn_id:
            return
        conn = self._conns[conn_id]
        if not conn.access.may_publish(path):
            self._deny(conn_id, "publish", path)
            conn.session.close(ErrorCode.UNAUTHORIZED, "not allowed to publish this path")
            # handle() still returns conn_id, so its close goes out with this flush.
            self._touched |= self.remove_connection(conn_id)
            return
        if owner is not None:
            self._withdraw(path)  # a new publisher takes over
        self._owners[path] = conn_id
        self._hops[path] = event.hop_count + 1
        conn.broadcasts.add(path)
        for other_id, other in self._conns.items():
            if other_id != conn_id and other.access.may_subscribe(path):
                other.session.publish(path, event.hop_count + 1)
                self._touched.add(other_id)

    def _withdraw(self, path: str) -> None:
        owner = self._owners.pop(path, None)
        self._hops.pop(path, None)
        if owner is None:
            return
        owner_conn = self._conns.get(owner)
        if owner_conn is not None:
            owner_conn.broadcasts.discard(path)
        for other_id, other in self._conns.items():
            if other_id != owner:
                other.session.unpublish(path)
                self._touched.add(other_id)
        for track in [t for t in self._tracks.values() if t.key[0] == path]:
            self._end_track(track, ErrorCode.GONE)

    # ------------------------------------------------------------- subscriptions

    def _on_viewer_subscribe(self, conn_id: ConnId, conn: _Conn, e: SubscribeRequested) -> None:
        self._touched.add(conn_id)
        if not conn.access.may_subscribe(e.broadcast):
            self._deny(conn_id, "subscribe", e.broadcast)
            conn.session.reject_subscribe(e.request_id, ErrorCode.UNAUTHORIZED)
            return
        owner = self._owners.get(e.broadcast)
        # A closed publisher session has a SessionError waiting to be handled: treat as gone.
        if owner is None or owner == conn_id or self._conns[owner].session.closed:
            conn.session.reject_subscribe(e.request_id, ErrorCode.NOT_FOUND)
            return
        key = (e.broadcast, e.track)
        track = self._tracks.get(key)
        if track is not None:
            held = sum(1 for viewer_conn, _ in track.viewers if viewer_conn == conn_id)
            if held >= self.max_subscriptions_per_track:
                conn.stats.subscribes_refused += 1
                if conn.stats.subscribes_refused > MAX_REFUSED_SUBSCRIBES:
                    # No player asks this often past the limit: a flood, whose every
                    # refusal costs the relay the time the honest viewers need.
                    conn.session.close(ErrorCode.LIMIT_EXCEEDED, "too many refused subscriptions")
                    self._touched |= self.remove_connection(conn_id)
                    return
                conn.session.reject_subscribe(e.request_id, ErrorCode.LIMIT_EXCEEDED)
                return
        if track is None:
            publisher = self._conns[owner]
            subscription_id = publisher.session.subscribe(e.broadcast, e.track, priority=e.priority)
            publisher.upstream[subscription_id] = key
            track = _Track(key, owner, subscription_id)
            self._tracks[key] = track
            self._touched.add(owner)
        viewer = _Viewer(conn_id, e.request_id, self._latency(e.max_latency_ms))
        track.viewers[(conn_id, e.request_id)] = viewer
        if track.accepted:
            self._start_viewer(track, viewer)

    def _on_viewer_cancel(self, conn_id: ConnId, request_id: int) -> None:
        for track in list(self._tracks.values()):
            if (conn_id, request_id) in track.viewers:
                self._remove_viewer(track, (conn_id, request_id))
                return

    def _start_viewer(self, track: _Track, viewer: _Viewer) -> None:
        """Accept a viewer and replay the cached latest group, if any."""
        if viewer.accepted:
            return
        session = self._conns[viewer.conn].session
        viewer.accepted = session.accept_subscribe(viewer.request_id)
        self._touched.add(viewer.conn)
        if track.latest is None:
            return  # the publisher's first group comes with its subscription's keyframe
        group = track.groups[track.latest]
        if not group.cacheable or (group.done and not group.complete):
            self._nudge(track, self._clock())
            return  # joins at the next group's start
        out = self._open_out(track, viewer, track.latest, group)
        if out is None:
            return
        for payload in group.frames:
            self._write(viewer, out, payload)
        if group.done:
            self._finish_out(viewer, out)
            del viewer.outs[track.latest]

    def _remove_viewer(self, track: _Track, key: ViewerKey) -> None:
        viewer = track.viewers.pop(key)
        conn = self._conns.get(viewer.conn)
        if conn is not None:
            for out in viewer.outs.values():
                conn.session.abort_group(out.stream_id, ErrorCode.CANCEL)
            self._touched.add(viewer.conn)
        if not track.viewers:
            self._end_track(track, ErrorCode.CANCEL)

    def _end_track(self, track: _Track, code: ErrorCode) -> None:
        """Drop a track: unsubscribe upstream, end (or refuse) every viewer's subscription."""
        if self._tracks.get(track.key) is not track:
            return
        del self._tracks[track.key]
        publisher = self._conns.get(track.publisher)
        if publisher is not None:
            publisher.upstream.pop(track.subscription_id, None)
            publisher.session.unsubscribe(track.subscription_id)
            self._touched.add(track.publisher)
        for viewer in track.viewers.values():
            conn = self._conns.get(viewer.conn)
            if conn is None:
                continue
            self._touched.add(viewer.conn)
            for out in viewer.outs.values():
                conn.session.abort_group(out.stream_id, code)
            if viewer.accepted:
                conn.session.end_subscription(viewer.request_id)
            else:
                conn.session.reject_subscribe(viewer.request_id, code)
        track.viewers.clear()

    # -------------------------------------------------------------------- groups

    def _on_group_opened(self, conn: _Conn, e: GroupOpened) -> None:
        track = self._upstream_track(conn, e.subscription_id)
        if track is None:
            return
        group = _Group(e.sequence)
        track.groups[e.stream_id] = group
        latest = None if track.latest is None else track.groups.get(track.latest)
        if latest is not None and latest.sequence > e.sequence:
            # A late, older group (its first packet was lost and came back after a newer
            # group's): nobody new starts there, but viewers that were already following
            # get it, as any group: QUIC does not order streams, so this is routine.
            group.cacheable = False
            for viewer in list(track.viewers.values()):
                if viewer.accepted and viewer.start is not None and viewer.start <= e.sequence:
                    self._open_out(track, viewer, e.stream_id, group)
            return
        if latest is not None and track.latest is not None and latest.done:
            del track.groups[track.latest]
        elif latest is not None:
            latest.frames.clear()
            latest.cacheable = False
        track.latest = e.stream_id
        now = self._clock()
        for viewer in list(track.viewers.values()):
            if not viewer.accepted:
                continue
            for upstream, out in list(viewer.outs.items()):
                if self._lagging(viewer, out, now):
                    self._skip(viewer, upstream)
            self._check_tails(viewer, now)
            self._open_out(track, viewer, e.stream_id, group)

    def _on_frame(self, conn: _Conn, e: FrameReceived) -> None:
        conn.stats.frames_in += 1
        conn.stats.bytes_in += len(e.payload)
        track = self._upstream_track(conn, e.subscription_id)
        group = None if track is None else track.groups.get(e.stream_id)
        if track is None or group is None:
            return
        if group.cacheable:
            group.frames.append(e.payload)
            group.cached_bytes += len(e.payload)
            if group.cached_bytes > self.max_group_cache_bytes:
                group.frames.clear()  # new viewers wait for the next group instead
                group.cacheable = False
        now = self._clock()
        for viewer in list(track.viewers.values()):
            out = viewer.outs.get(e.stream_id)
            if out is None:
                continue
            if self._lagging(viewer, out, now):
                self._skip(viewer, e.stream_id)
                self._nudge(track, now)
            else:
                self._write(viewer, out, e.payload)
        if self._on_frame_hook is not None:
            self._on_frame_hook(track.key, len(e.payload), self._clock() - now)

    def _on_group_closed(self, conn: _Conn, e: GroupClosed) -> None:
        track = self._upstream_track(conn, e.subscription_id)
        group = None if track is None else track.groups.get(e.stream_id)
        if track is None or group is None:
            return
        group.done = True
        group.complete = e.complete
        for viewer in track.viewers.values():
            out = viewer.outs.pop(e.stream_id, None)
            if out is None:
                continue
            if e.complete:
                self._finish_out(viewer, out)
            else:
                session = self._conns[viewer.conn].session
                session.abort_group(out.stream_id, e.error_code or ErrorCode.CANCEL)
            self._touched.add(viewer.conn)
        if track.latest != e.stream_id:
            del track.groups[e.stream_id]

    def _open_out(
        self, track: _Track, viewer: _Viewer, upstream: int, group: _Group
    ) -> _Out | None:
        conn = self._conns[viewer.conn]
        stream_id = conn.session.open_group(viewer.request_id, group.sequence)
        self._touched.add(viewer.conn)
        if stream_id is None:
            if not conn.session.closed and conn.session.request(viewer.request_id) is not None:
                # The request is live, so the viewer's stream credit is used up (it stopped
                # reading): it misses this group, as a skipped viewer does, and the next
                # GroupOpened tries again from that group's start.
                conn.stats.groups_skipped += 1
            return None
        out = _Out(stream_id)
        viewer.outs[upstream] = out
        if viewer.start is None:
            viewer.start = group.sequence
        return out

    def _write(self, viewer: _Viewer, out: _Out, payload: bytes) -> None:
        conn = self._conns[viewer.conn]
        if conn.session.write_frame(out.stream_id, payload):
            out.written += len(payload)
            out.marks.append((out.written, self._clock()))
            conn.stats.frames_out += 1
            conn.stats.bytes_out += len(payload)
            self._touched.add(viewer.conn)

    def _finish_out(self, viewer: _Viewer, out: _Out) -> None:
        """FIN a viewer's group stream; until its bytes are sent they count as backlog."""
        self._conns[viewer.conn].session.finish_group(out.stream_id)
        if self._buffered_bytes(viewer.conn, out.stream_id) > 0:
            viewer.tails[out.stream_id] = out

    def _tails_lagging(self, viewer: _Viewer, now: float) -> tuple[int, bool]:
        """(unsent bytes of the finished groups, whether one holds a frame older than
        the viewer's max latency); forgets the tails that drained."""
        total = 0
        stale = False
        for stream_id, tail in list(viewer.tails.items()):
            backlog = self._buffered_bytes(viewer.conn, stream_id)
            if backlog <= 0:
                del viewer.tails[stream_id]  # drained (or reset by the peer)
                continue
            total += backlog
            stale = stale or self._too_old(viewer, tail, backlog, now)
        return total, stale

    def _too_old(self, viewer: _Viewer, out: _Out, backlog: int, now: float) -> bool:
        # Frames entirely below (written - backlog) have left our queue; forget their marks.
        sent = out.written - backlog
        while out.marks and out.marks[0][0] <= sent:
            out.marks.popleft()
        if viewer.max_latency_s is None or not out.marks:
            return False
        return now - out.marks[0][1] > viewer.max_latency_s

    def _lagging(self, viewer: _Viewer, out: _Out, now: float) -> bool:
        """Whether the viewer is behind: too many bytes queued for it, or a frame older
        than its max latency still unsent, in this group or in a finished one. Short
        groups (a keyframe every few frames) finish before their frames grow old, so the
        finished groups count as well as the current one."""
        backlog = self._buffered_bytes(viewer.conn, out.stream_id)
        tail_backlog, stale_tail = self._tails_lagging(viewer, now)
        if backlog + tail_backlog > self.max_backlog_bytes:
            return True
        return stale_tail or self._too_old(viewer, out, backlog, now)

    def _skip(self, viewer: _Viewer, upstream: int) -> None:
        out = viewer.outs.pop(upstream)
        conn = self._conns[viewer.conn]
        conn.session.abort_group(out.stream_id, ErrorCode.SKIPPED)
        conn.stats.groups_skipped += 1
        self._skip_tails(viewer)
        self._touched.add(viewer.conn)
        # The next GroupOpened gives this viewer a fresh stream from that group's start.

    def _nudge(self, track: _Track, now: float) -> None:
        """Ask the track's publisher for a keyframe the only way moq-lite can (module doc)."""
        if track.nudged_at is not None and now - track.nudged_at < self.nudge_interval_s:
            return
        publisher = self._conns.get(track.publisher)
        if publisher is None or publisher.session.closed:
            return
        track.nudged_at = now
        broadcast, name = track.key
        publisher.nudges.add(publisher.session.subscribe(broadcast, name))
        publisher.stats.keyframe_nudges += 1
        self._touched.add(track.publisher)

    def _check_tails(self, viewer: _Viewer, now: float) -> bool:
        """Skip a viewer's finished groups when they alone make it lag (between groups,
        or with a quiet publisher, there is no current group to notice it); whether it
        did."""
        if not viewer.tails:
            return False
        backlog, stale = self._tails_lagging(viewer, now)
        if stale or backlog > self.max_backlog_bytes:
            self._skip_tails(viewer)
            self._touched.add(viewer.conn)
            return True
        return False

    def _skip_tails(self, viewer: _Viewer) -> None:
        """Reset the finished groups still queued for a viewer that skips ahead: they are
        older than the group it skipped."""
        conn = self._conns[viewer.conn]
        for stream_id in viewer.tails:
            if conn.session.abort_finished_group(stream_id, ErrorCode.SKIPPED):
                conn.stats.groups_skipped += 1
        viewer.tails.clear()

    # ------------------------------------------------------------------- helpers

    def _deny(self, conn_id: ConnId, action: str, path: str) -> None:
        if self._on_denied is not None:
            self._on_denied(conn_id, action, path)

    def _upstream_track(self, conn: _Conn, subscription_id: int) -> _Track | None:
        key = conn.upstream.get(subscription_id)
        return None if key is None else self._tracks.get(key)

    def _find_viewer(self, conn_id: ConnId, request_id: int) -> _Viewer | None:
        for track in self._tracks.values():
            viewer = track.viewers.get((conn_id, request_id))
            if viewer is not None:
                return viewer
        return None

    def _latency(self, max_latency_ms: int) -> float | None:
        return max_latency_ms / 1000 if max_latency_ms else self.default_max_latency_s

    def _take_touched(self) -> set[ConnId]:
        touched = {c for c in self._touched if c in self._conns}
        self._touched.clear()
        return touched
