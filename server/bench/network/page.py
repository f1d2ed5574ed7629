"""What the player page shows, read from outside, for ``upcast bench network``.

Shown frames are timed where they are shown: an init script wraps the canvas's
``drawImage`` and notes ``performance.now()`` each time a ``VideoFrame`` is drawn
(client_web/src/renderer.ts draws each presented frame once, so this is
independent of what the page counts about itself). Freezes are gaps of more than
``FREEZE_MS`` between two drawn frames, and a gap still open when the window ends.

The page's own honest counters (lost, skipped, freezes, late, ...) are read from
``window.upcast.stats()`` when the page has them, as differences over the window.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from typing import Any

from server.serve.snapshots import FrameThumbs, shown_psnr
from server.session.feedback import FREEZE_MS

DRAW_WATCH = """
(() => {
  const draws = [];
  const draw = CanvasRenderingContext2D.prototype.drawImage;
  CanvasRenderingContext2D.prototype.drawImage = function (...args) {
    if (typeof VideoFrame !== "undefined" && args[0] instanceof VideoFrame) {
      draws.push(performance.now());
      if (draws.length > 200000) draws.splice(0, 100000);
    }
    return draw.apply(this, args);
  };
  window.__benchDraws = () => ({ draws: draws.splice(0), now: performance.now() });
})();
"""
READ_DRAWS = "() => window.__benchDraws ? window.__benchDraws() : { draws: [], now: 0 }"

# Cumulative counters of stats() that the window reports as differences (when present).
PAGE_COUNTERS = (
    "framesReceived",
    "framesPresented",
    "framesLost",
    "groupsSkipped",
    "freezes",
    "freezeMs",
    "late",
    "dropped",
    "skippedUndecodable",
    "bytesReceived",
    "timingGaps",
)


@dataclass
class ShownFrames:
    """Draw times (page ms) of the frames shown in the window, and the freezes between."""

    threshold_ms: float = FREEZE_MS
    shown: int = 0
    freezes: int = 0
    freeze_ms: float = 0.0
    longest_ms: float = 0.0
    _last_ms: float | None = None
    _origin_ms: float | None = None  # page time at the window's start (its last draw before)
    gaps_ms: list[float] = field(default_factory=list)
    # When each freeze began, seconds into the window (a step in a profile's schedule
    # and the freezes it caused line up).
    starts_s: list[float] = field(default_factory=list)

    def start(self, draws: list[float]) -> None:
        """Draws before the window: only the last one matters (the first gap's start)."""
        if draws:
            self._last_ms = self._origin_ms = draws[-1]

    def add(self, draws: list[float]) -> None:
        for t in draws:
            if self._origin_ms is None:
                self._origin_ms = t
            if self._last_ms is not None:
                self._gap(t - self._last_ms)
            self._last_ms = t
            self.shown += 1

    def finish(self, page_now_ms: float) -> None:
        """A picture still frozen when the window closes counts up to now."""
        if self._last_ms is not None:
            gap = page_now_ms - self._last_ms
            if gap > self.threshold_ms:
                self._gap(gap)
            self._last_ms = page_now_ms

    def _gap(self, gap_ms: float) -> None:
        if gap_ms > self.threshold_ms:
            self.freezes += 1
            self.freeze_ms += gap_ms
            self.longest_ms = max(self.longest_ms, gap_ms)
            self.gaps_ms.append(round(gap_ms, 1))
            if self._last_ms is not None and self._origin_ms is not None:
                self.starts_s.append(round((self._last_ms - self._origin_ms) / 1000, 2))

    def summary(self) -> dict[str, Any]:
        return {
            "count": self.freezes,
            "total_ms": round(self.freeze_ms, 1),
            "longest_ms": round(self.longest_ms, 1),
            "gaps_ms": self.gaps_ms,
            "starts_s": self.starts_s,
        }


def counter_deltas(start: dict[str, Any], end: dict[str, Any]) -> dict[str, Any]:
    """The page's counters over the window; absent ones are left out (an older page)."""
    out: dict[str, Any] = {}
    for key in PAGE_COUNTERS:
        a, b = start.get(key), end.get(key)
        if isinstance(a, int | float) and isinstance(b, int | float):
            out[key] = round(b - a, 1)
    if isinstance(end.get("longestFreezeMs"), int | float):
        out["longestFreezeMs_since_start"] = round(float(end["longestFreezeMs"]), 1)
    recovery = end.get("recovery")
    first = start.get("recovery")
    if isinstance(recovery, dict) and isinstance(first, dict):
        for key in ("keyframeRequests", "recoveries"):
            if isinstance(recovery.get(key), int) and isinstance(first.get(key), int):
                out[f"recovery_{key}"] = recovery[key] - first[key]
    return out


@dataclass
class PictureQuality:
    """PSNR of canvas snapshots against the session's frame with the same id."""

    samples_db: list[float] = field(default_factory=list)
    unknown: int = 0  # snapshots whose frame the tap no longer (or never) had

    def snapshot(self, page: Any, thumbs: FrameThumbs) -> None:
        db = shown_psnr(page, thumbs)
        if db is None:
            self.unknown += 1
        else:
            self.samples_db.append(db)

    def summary(self) -> dict[str, Any]:
        s = sorted(self.samples_db)
        if not s:
            return {"count": 0, "unknown": self.unknown, "median": None, "min": None}
        return {
            "count": len(s),
            "unknown": self.unknown,
            "median": round(statistics.median(s), 2),
            "min": round(s[0], 2),
        }
