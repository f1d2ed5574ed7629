"""A load-test viewer's feedback, sent the way the browser sends it.

The viewer publishes its own broadcast ``<broadcast>/input/<id>`` on the link it
watches through (client_web/src/input.ts does the same); the session asks the relay
for announces under ``<broadcast>/input`` and subscribes each ``input`` track
(server/session/broadcast.py). One group stays open per subscription, so the
messages arrive in order on one QUIC stream; a group the peer cancels is replaced
by a new one at the next message.

Every ``FEEDBACK_INTERVAL_MS`` the viewer calls ``send``: one ``feedback`` message
(server/session/feedback.py) with the frames that arrived since the last one, as
``[pts_us, arrival_ms]`` on this process's monotonic clock, and the cumulative
counters. Frames noted while nobody subscribes wait, up to ``MAX_FEEDBACK_FRAMES``
(the newest kept: the counters are cumulative, so nothing else is lost).
"""

from __future__ import annotations

import json
import time
import uuid
from collections import deque
from dataclasses import dataclass

from server.moq.events import Event, SubscribeCancelled, SubscribeRequested
from server.moq.session import MoqSession
from server.session.feedback import MAX_FEEDBACK_FRAMES
from server.session.viewer_input import MAX_MESSAGE_BYTES

INPUT_TRACK = "input"
KEYFRAME_EVERY_MS = 1000.0  # keyframe requests: at most one a second while stuck


@dataclass(frozen=True)
class FeedbackCounts:
    """The cumulative counters of one message (FeedbackFields without the frames)."""

    bytes: int = 0
    lost: int = 0
    skipped: int = 0
    freezes: int = 0
    freeze_ms: float = 0.0
    late: int = 0


def monotonic_ms() -> float:
    return time.monotonic() * 1000.0


class FeedbackSender:
    def __init__(self, broadcast: str, *, player: bool = False, source_id: str | None = None):
        self.player = player
        self.path = (
            f"{broadcast.strip('/')}/input/{source_id or 'loadtest-' + uuid.uuid4().hex[:8]}"
        )
        self.sent = 0  # messages written to at least one subscriber
        self._seq = 0
        self._frames: deque[tuple[int, float]] = deque(maxlen=MAX_FEEDBACK_FRAMES)
        self._groups: dict[int, int | None] = {}  # request id -> open group stream
        self._next_group = 0
        self._last_counts = FeedbackCounts()
        self._last_keyframe_ms = -1e12
        self.keyframe_requests = 0

    def publish(self, moq: MoqSession) -> None:
        moq.publish(self.path)

    @property
    def subscribed(self) -> bool:
        return bool(self._groups)

    def on_events(self, moq: MoqSession, events: list[Event]) -> None:
        """Answer subscriptions to our input track; the caller flushes the link."""
        for event in events:
            if isinstance(event, SubscribeRequested):
                if event.broadcast.strip("/") != self.path or event.track != INPUT_TRACK:
                    moq.reject_subscribe(event.request_id)
                elif moq.accept_subscribe(event.request_id):
                    self._groups[event.request_id] = None
            elif isinstance(event, SubscribeCancelled):
                self._groups.pop(event.request_id, None)

    def note_frame(self, pts_us: int, arrival_ms: float) -> None:
        if pts_us >= 0:
            self._frames.append((pts_us, round(arrival_ms, 1)))

    def message(self, counts: FeedbackCounts, now_ms: float | None = None) -> bytes:
        """The next message (taking the noted frames); oldest frames go if it is too long."""
        self._seq += 1
        frames = list(self._frames)
        self._frames.clear()
        body: dict[str, object] = {
            "type": "feedback",
            "seq": self._seq,
            "sent_ms": round(monotonic_ms() if now_ms is None else now_ms, 1),
            "player": self.player,
            "bytes": counts.bytes,
            "lost": counts.lost,
            "skipped": counts.skipped,
            "freezes": counts.freezes,
            "freeze_ms": round(counts.freeze_ms, 1),
            "late": counts.late,
        }
        while True:
            wire = json.dumps({**body, "frames": frames}, separators=(",", ":")).encode()
            if len(wire) <= MAX_MESSAGE_BYTES or not frames:
                return wire
            frames = frames[len(frames) // 4 + 1 :]

    def wants_keyframe(self, counts: FeedbackCounts, stalled: bool, now_ms: float) -> bool:
        """Ask for a keyframe, as the page does (client_web/src/recovery.ts): a group
        was skipped or a frame lost since the last message, or nothing has arrived for
        a while (the relay reset our group; under intra refresh the next group starts
        only at a requested IDR). At most one request per ``KEYFRAME_EVERY_MS``."""
        last, self._last_counts = self._last_counts, counts
        broke = counts.skipped > last.skipped or counts.lost > last.lost
        if not (broke or stalled) or now_ms - self._last_keyframe_ms < KEYFRAME_EVERY_MS:
            return False
        self._last_keyframe_ms = now_ms
        return True

    def send(self, moq: MoqSession, counts: FeedbackCounts, *, stalled: bool = False) -> bool:
        """Write one message to every subscriber, and a keyframe request when
        ``wants_keyframe`` says so; False when nobody subscribes yet (the frames wait for
        the next try). The caller flushes the link."""
        if not self._groups or moq.closed:
            return False
        wire = self.message(counts)
        if self.wants_keyframe(counts, stalled, monotonic_ms()):
            self._seq += 1
            request = {"type": "keyframe", "seq": self._seq}
            wire_keyframe = json.dumps(request, separators=(",", ":")).encode()
            self.keyframe_requests += 1
        else:
            wire_keyframe = None
        written = False
        for request_id, stream in list(self._groups.items()):
            if moq.request(request_id) is None:  # the subscription ended meanwhile
                del self._groups[request_id]
                continue
            if stream is None or not moq.write_frame(stream, wire):
                stream = moq.open_group(request_id, self._next_group)
                self._next_group += 1
                self._groups[request_id] = stream
                if stream is None or not moq.write_frame(stream, wire):
                    self._groups[request_id] = None
                    continue
            if wire_keyframe is not None:
                moq.write_frame(stream, wire_keyframe)
            written = True
        if written:
            self.sent += 1
        return written
