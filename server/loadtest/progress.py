"""The one-line progress display (stderr) while a load test runs.

Fed with Snapshots from every process; fps shown is each viewer's rate over
the last interval (what it gets now, not a run average that hides a stall).
On a terminal the line is rewritten in place; otherwise (a log file) a line is
printed every few seconds so the log stays readable.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

import numpy as np

from .plan import RunPlan
from .viewer import Snapshot

PIPE_EVERY_S = 5.0


class ProgressBoard:
    def __init__(
        self, plan: RunPlan, viewers: int, *, label: str = "", stream: TextIO | None = None
    ) -> None:
        self.plan = plan
        self.viewers = viewers
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self._latest: dict[int, Snapshot] = {}
        self._previous: dict[int, Snapshot] = {}
        self._latency: list[float] = []
        self._tty = self.stream.isatty()
        self._last_print = 0.0
        self._width = 0

    def update(self, snap: Snapshot) -> None:
        before = self._latest.get(snap.worker)
        if before is not None:
            self._previous[snap.worker] = before
        self._latest[snap.worker] = snap
        self._latency.extend(snap.new_latency_ms)

    def line(self, now: float) -> str:
        plan = self.plan
        if now < plan.window_start:
            phase = "ramp" if now < plan.connect_at(self.viewers - 1) else "warm-up"
        elif now < plan.window_end:
            phase = (
                f"measure {now - plan.window_start:4.0f}/{plan.window_end - plan.window_start:.0f}s"
            )
        else:
            phase = "closing"
        connected = sum(s.connected for s in self._latest.values())
        failed = sum(s.failed for s in self._latest.values())
        fps: list[float] = []
        mbit = 0.0
        for worker, snap in self._latest.items():
            prev = self._previous.get(worker)
            if prev is None or snap.at <= prev.at:
                continue
            dt = snap.at - prev.at
            fps.extend((a - b) / dt for a, b in zip(snap.frames, prev.frames, strict=True))
            mbit += (snap.bytes_total - prev.bytes_total) * 8 / dt / 1e6
        fps_text = f"fps med {np.median(fps):4.1f} min {min(fps):4.1f}" if fps else "fps  -"
        p95 = f"{np.percentile(self._latency, 95):6.1f} ms" if self._latency else "     - "
        prefix = f"{self.label} " if self.label else ""
        elapsed = max(0.0, now - plan.start)
        return (
            f"{prefix}[{elapsed:5.1f}s {phase}] viewers {connected}/{self.viewers}"
            f" ({failed} failed) | {fps_text} | p95 publish->receive {p95} | {mbit:6.1f} Mbit/s"
        )

    def tick(self) -> None:
        now = time.monotonic()
        text = self.line(now)
        if self._tty:
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        elif now - self._last_print >= PIPE_EVERY_S:
            self.stream.write(text + "\n")
            self._last_print = now
        self.stream.flush()

    def finish(self) -> None:
        if self._tty and self._width:
            self.stream.write("\n")
            self.stream.flush()
