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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Frames whose timing record never arrives are forgotten after this many newer ones.
MAX_PENDING = 256


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

    def in_window(self, now_s: float) -> bool:
        return self.window[0] <= now_s < self.window[1]

    def on_video(
        self,
        pts_us: int | None,
        size: int,
        now_s: float,
        wall_us: int,
        duration_us: int | None = None,
    ) -> None:
        inside = self.in_window(now_s)
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

    def on_group(self, now_s: float) -> None:
        if self.in_window(now_s):
            self.groups += 1

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
