"""Prometheus gauges of the session's rate control (what an operator graphs per session)."""

from __future__ import annotations

from typing import ClassVar

from prometheus_client import CollectorRegistry, Counter, Gauge

from server.session.rate_control import RateState


class RateMetrics:
    _by_registry: ClassVar[dict[CollectorRegistry, RateMetrics]] = {}

    @classmethod
    def for_registry(cls, registry: CollectorRegistry) -> RateMetrics:
        """One set per registry: a second session on it (a test, a restart) shares it."""
        found = cls._by_registry.get(registry)
        if found is None:
            found = cls._by_registry[registry] = cls(registry)
        return found

    def __init__(self, registry: CollectorRegistry) -> None:
        self.bitrate = Gauge(
            "upcast_video_bitrate_bps", "Bitrate the encoder aims at now", registry=registry
        )
        self.received = Gauge(
            "upcast_player_received_bps",
            "Video throughput the slowest player reported over the last second",
            registry=registry,
        )
        self.queue = Gauge(
            "upcast_player_queue_seconds",
            "Queueing delay above the path's lowest, worst player",
            registry=registry,
        )
        self.fps_divisor = Gauge(
            "upcast_fps_divisor", "1: every frame encoded, 2: every other", registry=registry
        )
        self.changes = Counter(
            "upcast_bitrate_changes",
            "Times the rate control changed the bitrate",
            registry=registry,
        )

    def update(self, bitrate: int, state: RateState, fps_divisor: int) -> None:
        self.bitrate.set(bitrate)
        if state.delivered_bps is not None:
            self.received.set(state.delivered_bps)
        if state.queue_ms is not None:
            self.queue.set(state.queue_ms / 1000)
        self.fps_divisor.set(fps_divisor)
