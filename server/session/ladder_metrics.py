"""Prometheus series of the rendition ladder (what an operator weighs before --ladder off):
frames and bytes per rung, the CPU each rung's encoder used, frames the rungs skipped."""

from __future__ import annotations

from functools import partial

from prometheus_client import CollectorRegistry, Counter, Gauge

from server.media.ladder import RenditionLadder, Rung, RungFrame
from server.session.ladder_thread import LadderThread


def _cpu_seconds(rung: Rung) -> float:
    return rung.cpu_s_total


class LadderMetrics:
    def __init__(
        self, registry: CollectorRegistry, ladder: RenditionLadder, thread: LadderThread
    ) -> None:
        self._frames = Counter(
            "upcast_ladder_frames",
            "Frames published on a rung of the rendition ladder",
            ["track"],
            registry=registry,
        )
        self._bytes = Counter(
            "upcast_ladder_bytes",
            "Bytes published on a rung of the rendition ladder",
            ["track"],
            registry=registry,
        )
        cpu = Gauge(
            "upcast_ladder_cpu_seconds",
            "CPU seconds a rung's scaling and encoding used so far (its thread's clock)",
            ["track"],
            registry=registry,
        )
        for rung in ladder.rungs:
            cpu.labels(rung.track).set_function(partial(_cpu_seconds, rung))
        skipped = Gauge(
            "upcast_ladder_skipped_frames",
            "Frames the ladder left out because it was still encoding an older one (a busy host)",
            registry=registry,
        )
        skipped.set_function(lambda: thread.stats.skipped)

    def published(self, frames: list[RungFrame]) -> None:
        for frame in frames:
            self._frames.labels(frame.track).inc()
            self._bytes.labels(frame.track).inc(len(frame.encoded.fragment))
