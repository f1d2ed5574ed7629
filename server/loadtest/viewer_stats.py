"""What one load-test viewer measured, and the summary over all viewers.

Latency is matched per frame: the viewer notes the wall-clock time at which a
video frame (one CMAF fragment) arrived complete, keyed by its decode time
(``pts_us`` from the fragment's tfdt), and when the frame's timing record
arrives it subtracts the server's ``publish`` and ``render_end`` stamps.

Everything that is reported is counted inside one measurement window shared by
all viewers (monotonic seconds, after the connection ramp and a warm-up): the
relay replays its cached group to a viewer that joins, and those frames are
seconds old on arrival; counting them would make latency a property of the
join, not of the relay under load.

Loss is counted from the timing records' publish counter ``n`` (the session
increments it by one per published frame): over the ``n`` range seen in the
window, every ``n`` whose video frame never arrived (skipped group, reset
stream, missing timing record in between) is a lost frame.

A publisher without a timing track (moq-rs, FFmpeg, any other MoQ publisher) has
no server stamps. Then loss is counted on the media clock: over the decode-time
range seen in the window, at one frame per frame duration, every frame time that
never arrived is lost. And latency is the media-clock delay: arrival wall time
minus decode time, less the smallest such difference in the window, so the frame
that came fastest counts 0 ms and the others show how much later than it they
came (what a player's jitter buffer must hold; the constant part of the delay,
publisher to the fastest frame, is not visible without the publisher's clock).

The honest counters (``DeliveryCounters``) need neither clock nor timing track,
only what arrives, as the browser counts them: frames lost are gaps in the CMAF
fragments' ``mfhd`` sequence numbers, groups skipped are gaps in the moq-lite
group sequence plus groups the relay reset before their end, and a freeze is
more than ``FREEZE_MS`` between two received frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from server.session.feedback import FREEZE_MS

# Frames whose timing record never arrives are forgotten after this many newer ones.
MAX_PENDING = 256
# Each group is its own QUIC stream, so the last fragments of one group may arrive after
# the first of the next: a sequence gap is a loss only once this many newer ones came.
REORDER_FRAGMENTS = 16
# A sequence number this far below the highest seen: the publisher numbers afresh (a new
# encoder after a resize, a restarted session), not a late fragment.
RESTART_BELOW = 1024
MAX_MISSING = 4096  # gaps longer than this are counted at once, not remembered one by one


@dataclass
class DeliveryCounters:
    """Frames lost, groups skipped or reset and freezes, from what arrives.

    Fed every event; ``counting`` says whether it adds to the figures (a window's
    counters see the events before the window too, so a gap that ends inside it is
    measured from the frame before)."""

    lost: int = 0
    skipped_groups: int = 0  # gaps in the group sequence
    reset_groups: int = 0  # groups reset by the relay (or publisher) before their end
    freezes: int = 0
    freeze_ms: float = 0.0
    longest_freeze_ms: float = 0.0
    _top_sequence: int | None = None
    _missing: dict[int, bool] = field(default_factory=dict)  # sequence -> counts when lost
    _top_group: int | None = None
    _last_arrival_s: float | None = None

    @property
    def last_arrival_s(self) -> float | None:
        """When the newest video frame arrived (time.monotonic()), None before any."""
        return self._last_arrival_s

    @property
    def skipped(self) -> int:
        """What the feedback message calls skipped: every group not played to its end."""
        return self.skipped_groups + self.reset_groups

    def on_fragment(self, sequence: int | None, now_s: float, counting: bool = True) -> None:
        """One video frame arrived complete; ``sequence`` from its mfhd (None: unreadable)."""
        last, self._last_arrival_s = self._last_arrival_s, now_s
        if last is not None and counting:
            gap_ms = (now_s - last) * 1000.0
            if gap_ms > FREEZE_MS:
                self.freezes += 1
                self.freeze_ms += gap_ms
                self.longest_freeze_ms = max(self.longest_freeze_ms, gap_ms)
        if sequence is None:
            return
        top = self._top_sequence
        if top is not None and sequence < top - RESTART_BELOW:
            self._settle(0)  # what was missing before the renumbering stays missing
            top = None
        if top is None:
            self._top_sequence = sequence
        elif sequence > top:
            gap = sequence - top - 1
            if gap > MAX_MISSING:
                self.lost += gap if counting else 0
            else:
                for missing in range(top + 1, sequence):
                    self._missing[missing] = counting
            self._top_sequence = sequence
        else:
            self._missing.pop(sequence, None)  # a late one: not lost after all
        self._settle(REORDER_FRAGMENTS)

    def on_group(self, sequence: int, counting: bool = True) -> None:
        top = self._top_group
        if top is not None and sequence > top + 1 and counting:
            self.skipped_groups += sequence - top - 1
        if top is None or sequence > top:
            self._top_group = sequence

    def on_group_reset(self, counting: bool = True) -> None:
        if counting:
            self.reset_groups += 1

    def settle(self) -> None:
        """Count every gap still open as lost (the stream is over for us)."""
        self._settle(0)

    def new_track(self) -> None:
        """The video moved to a new track (a new encoded size): its fragments and groups
        number afresh, and what the old track left missing stays missing."""
        self._settle(0)
        self._top_sequence = None
        self._top_group = None

    def _settle(self, keep: int) -> None:
        top = self._top_sequence
        while self._missing and top is not None:
            oldest = next(iter(self._missing))
            if top - oldest <= keep:
                break
            if self._missing.pop(oldest):
                self.lost += 1

    def summary(self) -> dict[str, Any]:
        return {
            "lost": self.lost,
            "skipped_groups": self.skipped_groups,
            "reset_groups": self.reset_groups,
            "freezes": self.freezes,
            "freeze_ms": round(self.freeze_ms, 1),
            "longest_freeze_ms": round(self.longest_freeze_ms, 1),
        }


@dataclass
class ViewerStats:
    viewer: int
    # [start, end) in time.monotonic() seconds; only frames arriving inside count.
    window: tuple[float, float] = (0.0, math.inf)
    connected: bool = False
    disconnected: bool = False  # the session ended before we closed it
    error: str | None = None
    connect_ms: float | None = None  # WebTransport + moq-lite session setup
    first_frame_ms: float | None = None  # connect start -> first video frame
    connect_started_s: float | None = None
    frames: int = 0  # video frames arriving in the window
    bytes: int = 0  # their payload bytes
    groups: int = 0  # video groups opened in the window
    received_total: int = 0  # every video frame (progress display)
    bytes_total: int = 0
    bad_fragments: int = 0
    catalog: bool = False  # a catalog naming a video track arrived
    publish_to_receive_ms: list[float] = field(default_factory=list)
    render_end_to_receive_ms: list[float] = field(default_factory=list)
    # Decode time -> arrival wall clock of video frames in the window (media-clock figures).
    _media_arrivals_us: dict[int, int] = field(default_factory=dict)
    _frame_duration_us: int | None = None
    _arrivals_us: dict[int, tuple[int, bool]] = field(default_factory=dict)
    _early_records: dict[int, dict[str, Any]] = field(default_factory=dict)
    _seen_n: set[int] = field(default_factory=set)  # timing records arriving in the window
    _matched_n: set[int] = field(default_factory=set)  # records whose video frame arrived
    # Since the viewer subscribed (what its feedback reports), and inside the window.
    delivery: DeliveryCounters = field(default_factory=DeliveryCounters)
    delivery_window: DeliveryCounters = field(default_factory=DeliveryCounters)

    def in_window(self, now_s: float) -> bool:
        return self.window[0] <= now_s < self.window[1]

    def on_video(
        self,
        pts_us: int | None,
        size: int,
        now_s: float,
        wall_us: int,
        duration_us: int | None = None,
        sequence: int | None = None,
    ) -> None:
        inside = self.in_window(now_s)
        self.delivery.on_fragment(sequence, now_s)
        self.delivery_window.on_fragment(sequence, now_s, counting=inside)
        if inside and pts_us is not None:
            self._media_arrivals_us.setdefault(pts_us, wall_us)
            if duration_us and self._frame_duration_us is None:
                self._frame_duration_us = duration_us
        self.received_total += 1
        self.bytes_total += size
        if self.first_frame_ms is None and self.connect_started_s is not None:
            self.first_frame_ms = (now_s - self.connect_started_s) * 1000.0
        if inside:
            self.frames += 1
            self.bytes += size
        if pts_us is None:
            return
        record = self._early_records.pop(pts_us, None)
        if record is not None:
            self._match(record, wall_us, inside)
            return
        self._arrivals_us[pts_us] = (wall_us, inside)
        if len(self._arrivals_us) > MAX_PENDING:
            self._arrivals_us.pop(next(iter(self._arrivals_us)))

    def on_group(self, now_s: float, sequence: int | None = None) -> None:
        inside = self.in_window(now_s)
        if inside:
            self.groups += 1
        if sequence is not None:
            self.delivery.on_group(sequence)
            self.delivery_window.on_group(sequence, counting=inside)

    def on_new_track(self) -> None:
        """The catalog moved the video to a new track (see DeliveryCounters.new_track)."""
        self.delivery.new_track()
        self.delivery_window.new_track()

    def on_group_reset(self, now_s: float) -> None:
        self.delivery.on_group_reset()
        self.delivery_window.on_group_reset(counting=self.in_window(now_s))

    def on_timing(self, record: dict[str, Any], now_s: float) -> None:
        n = record.get("n")
        if isinstance(n, int) and self.in_window(now_s):
            self._seen_n.add(n)
        pts = record.get("pts_us")
        if not isinstance(pts, int):
            return
        arrival = self._arrivals_us.pop(pts, None)
        if arrival is None:  # the timing frame overtook its video frame
            self._early_records[pts] = record
            if len(self._early_records) > MAX_PENDING:
                self._early_records.pop(next(iter(self._early_records)))
            return
        self._match(record, *arrival)

    def _match(self, record: dict[str, Any], wall_us: int, inside: bool) -> None:
        n = record.get("n")
        if isinstance(n, int):
            self._matched_n.add(n)
        if not inside:
            return
        stamps = record.get("stamps", {})
        publish, render_end = stamps.get("publish"), stamps.get("render_end")
        if isinstance(publish, int):
            self.publish_to_receive_ms.append((wall_us - publish) / 1000.0)
        if isinstance(render_end, int):
            self.render_end_to_receive_ms.append((wall_us - render_end) / 1000.0)

    @property
    def published(self) -> int:
        """Frames the publisher sent during the window, as far as this viewer can tell."""
        if not self._seen_n:
            return self._media_expected()
        return max(self._seen_n) - min(self._seen_n) + 1

    def _media_expected(self) -> int:
        """Frames the media clock says were due in the window's decode-time range."""
        step = self._frame_duration_us
        if not self._media_arrivals_us or not step:
            return 0
        low, high = min(self._media_arrivals_us), max(self._media_arrivals_us)
        return round((high - low) / step) + 1

    def media_delay_ms(self) -> list[float]:
        """Arrival minus decode time, less the smallest in the window (see the module doc)."""
        if not self._media_arrivals_us:
            return []
        offsets = [wall - pts for pts, wall in self._media_arrivals_us.items()]
        fastest = min(offsets)
        return [(o - fastest) / 1000.0 for o in offsets]

    @property
    def lost(self) -> int:
        if not self._seen_n:  # no timing track: the media clock
            return max(0, self._media_expected() - len(self._media_arrivals_us))
        low, high = min(self._seen_n), max(self._seen_n)
        got = sum(1 for n in self._matched_n if low <= n <= high)
        return (high - low + 1) - got

    def window_s(self) -> float:
        start, end = self.window
        return end - start if math.isfinite(end) else 0.0

    def fps(self) -> float:
        span = self.window_s()
        return self.frames / span if span > 0 else 0.0

    def mbit_s(self) -> float:
        span = self.window_s()
        return self.bytes * 8 / span / 1e6 if span > 0 else 0.0

    def drop_pending(self) -> None:
        """Forget the unmatched frames (nothing will match them now; keeps pickles small)."""
        self._arrivals_us.clear()
        self._early_records.clear()
        self.delivery.settle()
        self.delivery_window.settle()

    def summary(self) -> dict[str, Any]:
        return {
            "viewer": self.viewer,
            "connected": self.connected,
            "disconnected": self.disconnected,
            "error": self.error,
            "connect_ms": _round(self.connect_ms),
            "first_frame_ms": _round(self.first_frame_ms),
            "frames": self.frames,
            "fps": round(self.fps(), 2),
            "lost": self.lost,
            "published": self.published,
            "groups": self.groups,
            "bytes": self.bytes,
            "mbit_s": round(self.mbit_s(), 3),
            "bad_fragments": self.bad_fragments,
            "catalog": self.catalog,
            "publish_to_receive_ms": percentiles(self.publish_to_receive_ms),
            "render_end_to_receive_ms": percentiles(self.render_end_to_receive_ms),
            "media_delay_ms": percentiles(self.media_delay_ms()),
            # In the window, counted as the browser counts (see DeliveryCounters).
            "delivery": self.delivery_window.summary(),
        }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 2)


def percentiles(samples: list[float]) -> dict[str, float | int]:
    if not samples:
        return {"count": 0}
    arr = np.asarray(samples, dtype=np.float64)
    p50, p95, p99 = np.percentile(arr, [50, 95, 99])
    return {
        "count": int(arr.size),
        "p50": round(float(p50), 3),
        "p95": round(float(p95), 3),
        "p99": round(float(p99), 3),
        "max": round(float(arr.max()), 3),
    }
