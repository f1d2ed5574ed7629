"""What one viewer's feedback says about its path: throughput, queueing delay, loss.

Delay-based, in the spirit of Google Congestion Control's receive-side estimator:
a frame's one-way delay is its arrival on the viewer's clock minus its send on
ours. The two clocks have an unknown offset, so only changes mean anything: the
lowest delay of the last ``BASE_WINDOW_S`` is the empty-queue path, and how far
the least delayed frame of the last ``QUEUE_WINDOW_S`` sits above it is the
queue that builds when we send faster than the path carries. The least delayed,
not the median: a queue delays every frame, while a busy viewer (its page's
main thread, a loaded machine) stamps some arrivals late; the minimum sees the
first and not the second. A queue shows up a few frames after the rate exceeds the
capacity, long before loss (a drop-tail buffer of 100 ms at a home router, or
the relay's QUIC sender holding data back), which is why the rate controller
reacts to it first.

Only what the session can check is used: a frame counts when its pts is one we
sent, with the size we sent, so a viewer cannot report more throughput than the
stream carried; counters that go backwards count as zero; a pts reported twice
counts once.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from server.session.feedback import FeedbackFields

BASE_WINDOW_S = 10.0  # the empty-queue delay is the lowest seen this long
RATE_WINDOW_S = 1.0  # throughput over the last second of arrivals
STALL_S = 1.0  # reports without a new frame for this long, while we send: nothing arrives
QUEUE_WINDOW_S = 0.3  # queueing delay: the least delayed frame of the last 0.3 s
SENT_HISTORY = 1200  # frames remembered for matching reports (20 s at 60 fps)


@dataclass(frozen=True)
class SentFrame:
    sent_s: float  # monotonic, when the session handed it to the link
    size: int  # bytes of the fragment


class SendLog:
    """The frames the session sent lately, by pts, for checking what viewers report."""

    def __init__(self, capacity: int = SENT_HISTORY) -> None:
        self._frames: dict[int, SentFrame] = {}
        self._order: deque[int] = deque()
        self._capacity = capacity

    def add(self, pts_us: int, size: int, now_s: float) -> None:
        if pts_us in self._frames:
            return
        self._frames[pts_us] = SentFrame(now_s, size)
        self._order.append(pts_us)
        while len(self._order) > self._capacity:
            self._frames.pop(self._order.popleft(), None)

    def get(self, pts_us: int) -> SentFrame | None:
        return self._frames.get(pts_us)

    def bits_per_second(self, now_s: float, window_s: float = RATE_WINDOW_S) -> float:
        """What the session sent over the last ``window_s``."""
        total = 0
        for pts in reversed(self._order):
            frame = self._frames[pts]
            if frame.sent_s < now_s - window_s:
                break
            total += frame.size
        return total * 8 / window_s


@dataclass
class LinkSample:
    """The estimate after a report; ``None`` where there were too few frames to say."""

    delivered_bps: float | None
    queue_ms: float | None
    queue_rising: bool
    # How much longer the last second of frames took to arrive than to be sent: above 1
    # the path is slower than the stream (a queue grows); a busy viewer stamping a few
    # frames late stretches nothing over a second, so this tells the two apart.
    stretch: float | None
    loss: float  # fraction of video frames lost since the previous report
    skipped: int  # groups skipped since the previous report
    freezes: int  # freezes since the previous report
    # Reports have brought no new frame for STALL_S while the session sent: the viewer
    # receives nothing (an outage, or a reset group it waits to replace). The delay
    # figures above are then None: they would describe frames from before.
    stalled: bool = False
    # The viewer's own byte counter over the time between its last two reports (our
    # clock), never more than we sent meanwhile: a throughput figure even when too few
    # frames arrived to time them (heavy loss), only ever too low if it lies.
    reported_bps: float | None = None


@dataclass
class _Arrival:
    arrival_ms: float
    delay_ms: float  # arrival (viewer clock) - send (our clock): offset unknown, constant
    size: int
    sent_ms: float


class LinkEstimate:
    """One viewer's path, from its feedback reports."""

    def __init__(self) -> None:
        self._arrivals: deque[_Arrival] = deque()
        self._seen: set[int] = set()
        self._seen_order: deque[int] = deque()
        self._last_counts = FeedbackFields()
        self._last_new_frame_s: float | None = None
        self._last_report_s: float | None = None
        self.frames_matched = 0
        self.frames_unverified = 0  # reported pts the session never sent (or forgot)

    def report(self, fields: FeedbackFields, log: SendLog, now_s: float) -> LinkSample:
        matched = self.frames_matched
        for pts, arrival_ms in fields.frames:
            if pts in self._seen:
                continue
            sent = log.get(pts)
            if sent is None:
                self.frames_unverified += 1
                continue
            self._remember(pts)
            self.frames_matched += 1
            sent_ms = sent.sent_s * 1000
            self._arrivals.append(_Arrival(arrival_ms, arrival_ms - sent_ms, sent.size, sent_ms))
        self._drop_old()
        fresh = self.frames_matched > matched
        if fresh or self._last_new_frame_s is None:
            self._last_new_frame_s = now_s
        quiet_s = now_s - self._last_new_frame_s
        sending = log.bits_per_second(now_s, STALL_S) > 0
        loss = self._loss(fields)
        reported = self._reported_bps(fields, log, now_s)
        skipped = max(0, fields.skipped - self._last_counts.skipped)
        freezes = max(0, fields.freezes - self._last_counts.freezes)
        self._last_counts = fields.model_copy(update={"frames": []})
        if not fresh:
            return LinkSample(
                delivered_bps=None,
                queue_ms=None,
                queue_rising=False,
                stretch=None,
                loss=loss,
                skipped=skipped,
                freezes=freezes,
                stalled=quiet_s >= STALL_S and sending,
                reported_bps=reported,
            )
        return LinkSample(
            delivered_bps=self._delivered_bps(),
            queue_ms=self._queue_ms(),
            queue_rising=self._queue_rising(),
            stretch=self._stretch(),
            loss=loss,
            skipped=skipped,
            freezes=freezes,
            reported_bps=reported,
        )

    def least_delay_ms(self, sent_from_ms: float, sent_to_ms: float) -> float | None:
        """The least one-way delay (with this viewer's clock offset) of the frames sent
        in ``[sent_from_ms, sent_to_ms)`` on our clock, or None if none arrived."""
        delays = [a.delay_ms for a in self._arrivals if sent_from_ms <= a.sent_ms < sent_to_ms]
        return min(delays) if delays else None

    def _remember(self, pts: int) -> None:
        self._seen.add(pts)
        self._seen_order.append(pts)
        if len(self._seen_order) > SENT_HISTORY:
            self._seen.discard(self._seen_order.popleft())

    def _drop_old(self) -> None:
        if not self._arrivals:
            return
        newest = self._arrivals[-1].arrival_ms
        while self._arrivals and self._arrivals[0].arrival_ms < newest - BASE_WINDOW_S * 1000:
            self._arrivals.popleft()

    def _recent(self, window_s: float) -> list[_Arrival]:
        if not self._arrivals:
            return []
        newest = self._arrivals[-1].arrival_ms
        return [a for a in self._arrivals if a.arrival_ms >= newest - window_s * 1000]

    def _delivered_bps(self) -> float | None:
        recent = self._recent(RATE_WINDOW_S)
        if len(recent) < 3:
            return None
        span_ms = recent[-1].arrival_ms - recent[0].arrival_ms
        # The first frame's bytes arrived before the window opened: count the rest.
        bits = sum(a.size for a in recent[1:]) * 8
        # A viewer claiming every frame arrived at once gets no more than the window.
        return bits / max(span_ms / 1000, RATE_WINDOW_S / 2)

    def _queue_ms(self) -> float | None:
        recent = self._recent(QUEUE_WINDOW_S)
        if len(recent) < 3:
            return None
        base = min(a.delay_ms for a in self._arrivals)
        return min(a.delay_ms for a in recent) - base

    def _reported_bps(self, fields: FeedbackFields, log: SendLog, now_s: float) -> float | None:
        last_s, self._last_report_s = self._last_report_s, now_s
        if last_s is None or now_s - last_s < 0.05 or fields.bytes == 0:
            return None  # no interval yet, or a viewer that does not count bytes
        interval = now_s - last_s
        got = max(0, fields.bytes - self._last_counts.bytes) * 8 / interval
        return min(got, log.bits_per_second(now_s, interval))

    def _stretch(self) -> float | None:
        recent = self._recent(RATE_WINDOW_S)
        if len(recent) < 4:
            return None
        sent = [a.sent_ms for a in recent]
        send_span = max(sent) - min(sent)
        if send_span < RATE_WINDOW_S * 1000 / 4:
            return None
        return (recent[-1].arrival_ms - recent[0].arrival_ms) / send_span

    def _queue_rising(self) -> bool:
        """The delay trend of the last half second (least squares over arrival time)
        goes up by more than 1 ms per 100 ms: the queue is filling now, not just high."""
        recent = self._recent(0.5)
        if len(recent) < 4:
            return False
        t0 = recent[0].arrival_ms
        xs = [a.arrival_ms - t0 for a in recent]
        ys = [a.delay_ms for a in recent]
        mean_x = sum(xs) / len(xs)
        mean_y = sum(ys) / len(ys)
        var = sum((x - mean_x) ** 2 for x in xs)
        if var <= 0:
            return False
        slope = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys, strict=True)) / var
        return slope > 0.01

    def _loss(self, fields: FeedbackFields) -> float:
        lost = max(0, fields.lost - self._last_counts.lost)
        received = len(fields.frames)
        return lost / (lost + received) if lost + received else 0.0
