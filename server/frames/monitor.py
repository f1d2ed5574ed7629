"""Frame-rate monitor: rolling fps, frame-interval jitter and per-stage latency.

The session and the relay each keep one. It sees every frame once (its arrival
time and, where known, its timing record), keeps a sliding window, warns in
the log when a stage's p95 misses its budget, and mirrors everything into
Prometheus metrics so an operator's dashboards see the same figures as the
page's overlay.

Budgets default to what a stream at ``target_fps`` can afford: the render,
upscale and encode stages each get one frame period (they run in parallel
processes, so each may take a whole period without lowering the rate); the
hand-offs and the publish step get a couple of milliseconds.

Warnings are summarised, not repeated: the first miss is logged at once, then at
most one line per ``WARN_EVERY_S`` names every budget missed since the last line and
in how many of the checks (one a second). A machine that cannot hold the target
would otherwise print a line per stage per window (52 in 90 s on 2 cores).
"""

from __future__ import annotations

import logging
import time
import weakref
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import numpy.typing as npt
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from server.frames.timing import STAGE_SPANS, span_ms

log = logging.getLogger(__name__)

WINDOW_S = 2.0
WARN_EVERY_S = 30.0
# Seconds; covers 0.1 ms hand-offs to half-second stalls.
LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2, 0.5)
SERVER_SPANS = ("render", "ring_r_handoff", "upscale", "ring_u_handoff", "encode", "publish")


def default_budgets_ms(target_fps: float) -> dict[str, float]:
    period_ms = 1000.0 / target_fps
    return {
        "render": period_ms,
        "ring_r_handoff": 2.0,
        "upscale": period_ms,
        "ring_u_handoff": 2.0,
        "encode": period_ms,
        "publish": 2.0,
    }


@dataclass(frozen=True)
class StageFigures:
    p50_ms: float
    p95_ms: float
    count: int


@dataclass(frozen=True)
class MonitorSnapshot:
    fps: float
    jitter_ms: float  # standard deviation of the frame interval over the window
    frames: int
    dropped: int
    stages: dict[str, StageFigures] = field(default_factory=dict)
    window_frames: int = 0  # frames in the window the rate was measured over

    def as_dict(self) -> dict[str, object]:
        return {
            "fps": round(self.fps, 2),
            "jitter_ms": round(self.jitter_ms, 3),
            "frames": self.frames,
            "dropped": self.dropped,
            "stages": {
                name: {"p50_ms": round(f.p50_ms, 3), "p95_ms": round(f.p95_ms, 3), "n": f.count}
                for name, f in self.stages.items()
            },
        }


class MonitorMetrics:
    """The Prometheus metrics of every monitor of one registry, labelled by component.

    One instance per registry (``for_registry``): a registry refuses a metric name
    twice, and a relay adds a monitor per broadcast."""

    _by_registry: ClassVar[weakref.WeakKeyDictionary[CollectorRegistry, MonitorMetrics]] = (
        weakref.WeakKeyDictionary()
    )

    @classmethod
    def for_registry(cls, registry: CollectorRegistry) -> MonitorMetrics:
        found = cls._by_registry.get(registry)
        if found is None:
            found = cls._by_registry[registry] = cls(registry)
        return found

    def __init__(self, registry: CollectorRegistry) -> None:
        labels = ["component"]
        self.fps = Gauge("upcast_fps", "Rolling frames per second", labels, registry=registry)
        self.jitter = Gauge(
            "upcast_frame_jitter_seconds",
            "Std-dev of the frame interval",
            labels,
            registry=registry,
        )
        self.frames = Counter("upcast_frames", "Frames seen", labels, registry=registry)
        self.dropped = Counter("upcast_dropped_frames", "Frames lost", labels, registry=registry)
        self.budget_misses = Counter(
            "upcast_stage_budget_misses",
            "Windows whose p95 missed the stage budget",
            [*labels, "stage"],
            registry=registry,
        )
        self.stage = Histogram(
            "upcast_stage_latency_seconds",
            "Latency of each pipeline stage (server/frames/timing.py defines the boundaries)",
            [*labels, "stage"],
            buckets=LATENCY_BUCKETS,
            registry=registry,
        )


class FrameRateMonitor:
    """Rolling figures over the last ``window_s`` seconds of frames."""

    def __init__(
        self,
        component: str,
        target_fps: float | None,
        *,
        registry: CollectorRegistry | None = None,
        budgets_ms: Mapping[str, float] | None = None,
        window_s: float = WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if target_fps is not None and target_fps <= 0:
            raise ValueError(f"target_fps must be positive, got {target_fps}")
        self.component = component
        # None: the rate is whatever the source sends (the relay does not know it).
        self.target_fps = target_fps
        self.window_s = window_s
        # Budgets left to their default follow the target when it changes.
        self._default_budgets = budgets_ms is None
        if budgets_ms is None:
            budgets_ms = default_budgets_ms(target_fps) if target_fps is not None else {}
        self.budgets_ms = dict(budgets_ms)
        self._clock = clock
        self._arrivals: deque[float] = deque()
        self._stages: dict[str, deque[tuple[float, float]]] = {}
        # Misses since the last summary line: how many checks missed each budget, and
        # the latest figures of each.
        self._checks = 0
        self._miss_counts: dict[str, int] = {}
        self._miss_figures: dict[str, str] = {}
        self._last_summary: float | None = None
        self.frames = 0
        self.dropped = 0
        self.metrics = MonitorMetrics.for_registry(registry) if registry is not None else None

    def set_target_fps(self, target_fps: float) -> None:
        """The source now runs at ``target_fps`` (the quality controller changed the frame
        rate): the rate is judged against it, and default budgets follow its period."""
        if not target_fps > 0:
            raise ValueError(f"target_fps must be positive, got {target_fps}")
        self.target_fps = target_fps
        if self._default_budgets:
            self.budgets_ms = default_budgets_ms(target_fps)

    def frame(self, stamps: npt.NDArray[np.int64] | None = None, *, dropped: int = 0) -> None:
        """Record one frame (its timing record, if any) and frames lost before it."""
        now = self._clock()
        self.frames += 1
        self.dropped += dropped
        self._arrivals.append(now)
        m = self.metrics
        if m is not None:
            m.frames.labels(self.component).inc()
            if dropped:
                m.dropped.labels(self.component).inc(dropped)
        if stamps is not None:
            for name, start, end in STAGE_SPANS:
                ms = span_ms(stamps, start, end)
                if ms is None or ms < 0:
                    continue
                self.record_stage(name, ms, now=now)
        self._trim(now)

    def record_stage(self, name: str, ms: float, *, now: float | None = None) -> None:
        """Record a stage latency measured elsewhere (the relay's relay stage, say)."""
        now = self._clock() if now is None else now
        self._stages.setdefault(name, deque()).append((now, ms))
        if self.metrics is not None:
            self.metrics.stage.labels(self.component, name).observe(ms / 1000.0)

    def _trim(self, now: float) -> None:
        horizon = now - self.window_s
        while self._arrivals and self._arrivals[0] < horizon:
            self._arrivals.popleft()
        for samples in self._stages.values():
            while samples and samples[0][0] < horizon:
                samples.popleft()

    def snapshot(self) -> MonitorSnapshot:
        now = self._clock()
        self._trim(now)
        arrivals = np.fromiter(self._arrivals, dtype=np.float64)
        fps = 0.0
        jitter_ms = 0.0
        if arrivals.size >= 2:
            span = arrivals[-1] - arrivals[0]
            fps = (arrivals.size - 1) / span if span > 0 else 0.0
            jitter_ms = float(np.std(np.diff(arrivals)) * 1000.0)
        stages: dict[str, StageFigures] = {}
        for name, samples in self._stages.items():
            if not samples:
                continue
            values = np.fromiter((ms for _, ms in samples), dtype=np.float64)
            p50, p95 = np.percentile(values, [50, 95])
            stages[name] = StageFigures(float(p50), float(p95), int(values.size))
        snap = MonitorSnapshot(
            fps, jitter_ms, self.frames, self.dropped, stages, window_frames=int(arrivals.size)
        )
        if self.metrics is not None:
            self.metrics.fps.labels(self.component).set(fps)
            self.metrics.jitter.labels(self.component).set(jitter_ms / 1000.0)
        return snap

    def check_budgets(self) -> list[str]:
        """Stages (and "fps") over budget now; the misses are logged in summaries."""
        snap = self.snapshot()
        now = self._clock()
        missed: dict[str, str] = {}
        # A full window below 90 % of the target rate is a missed frame budget too.
        target = self.target_fps
        if target is not None and len(self._arrivals) >= 2 and 0 < snap.fps < 0.9 * target:
            missed["fps"] = (
                f"{snap.fps:.1f} fps is below 90% of the {target:.0f} fps target "
                f"(jitter {snap.jitter_ms:.1f} ms)"
            )
        for name, budget in self.budgets_ms.items():
            figures = snap.stages.get(name)
            if figures is None or figures.p95_ms <= budget:
                continue
            missed[name] = (
                f"stage {name} p95 {figures.p95_ms:.1f} ms is over its {budget:.1f} ms budget "
                f"(p50 {figures.p50_ms:.1f} ms)"
            )
            if self.metrics is not None:
                self.metrics.budget_misses.labels(self.component, name).inc()
        self._checks += 1
        for name, figures_text in missed.items():
            self._miss_counts[name] = self._miss_counts.get(name, 0) + 1
            self._miss_figures[name] = figures_text
        due = self._last_summary is None or now - self._last_summary >= WARN_EVERY_S
        if self._miss_counts and due:
            self._summarise(now)
        return list(missed)

    def _summarise(self, now: float) -> None:
        parts = [
            f"{self._miss_figures[name]} [{count}/{self._checks} checks]"
            for name, count in self._miss_counts.items()
        ]
        log.warning(
            "%s: over budget: %s (next summary in %.0f s at the earliest)",
            self.component, "; ".join(parts), WARN_EVERY_S,
        )  # fmt: skip
        self._last_summary = now
        self._checks = 0
        self._miss_counts.clear()
        self._miss_figures.clear()
