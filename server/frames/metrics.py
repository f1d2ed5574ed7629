"""Prometheus metrics of the shared-memory rings, read from their shared headers."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from prometheus_client.core import CounterMetricFamily, Metric

from server.frames.ring import FrameRing

RING_FRAMES = "upcast_ring_frames"


def ring_metrics(rings: Iterable[FrameRing]) -> Iterator[Metric]:
    """Every ring's shared counters, labelled by ring name and outcome. Both sides
    of a ring read the same header: aggregate with ``max by (ring, outcome)``."""
    family = CounterMetricFamily(
        RING_FRAMES,
        "Frames through a shared-memory ring by outcome (dropped_overwritten: the "
        "real-time producer replaced a frame nobody read; rejected: truncated header)",
        labels=["ring", "outcome"],
    )
    for ring in rings:
        counters = ring.counters()
        for outcome in (
            "committed",
            "delivered",
            "dropped_overwritten",
            "dropped_skipped",
            "rejected",
            "recovered",
        ):
            family.add_metric([ring.name, outcome], getattr(counters, outcome))
    yield family
