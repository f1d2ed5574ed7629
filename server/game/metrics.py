"""Prometheus metrics of the game process (``--metrics-port``). Names are listed in
``GAME_METRICS`` (the Grafana dashboard test checks its queries against them)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import Metric
from prometheus_client.process_collector import ProcessCollector

from server.frames.metrics import RING_FRAMES, ring_metrics
from server.ops.metrics import STAGE_BUCKETS, _counter, _Snapshot

if TYPE_CHECKING:
    from server.game.loop import GameLoop

GAME_METRICS = (
    "upcast_game_frames_rendered",
    "upcast_game_frames_predicted",
    "upcast_game_frames_late",
    "upcast_game_ring_timeouts",
    "upcast_game_render_errors",
    "upcast_game_inputs_applied",
    "upcast_game_render_seconds",
    "upcast_game_dynamic_draw_seconds",
    RING_FRAMES,
)


def game_registry(loop: GameLoop) -> CollectorRegistry:
    """A registry with the game's metrics; also sets the loop's render and dynamic-draw hooks."""
    registry = CollectorRegistry()
    ProcessCollector(registry=registry)
    render = Histogram(
        "upcast_game_render_seconds",
        "Time to fully render one frame into ring R (render_start -> render_end)",
        buckets=STAGE_BUCKETS,
        registry=registry,
    )
    loop.on_render_time = render.observe
    dynamic = Histogram(
        "upcast_game_dynamic_draw_seconds",
        "Time to draw only the moving objects of a frame the worker predicts (frame generation)",
        buckets=STAGE_BUCKETS,
        registry=registry,
    )
    loop.on_dynamic_time = dynamic.observe

    def produce() -> Iterator[Metric]:
        s = loop.stats
        yield _counter(
            "upcast_game_frames_rendered", "Frames fully rendered into ring R", s.frames_rendered
        )
        yield _counter(
            "upcast_game_frames_predicted",
            "Frames into ring R with only the moving objects drawn (frame generation)",
            s.frames_predicted,
        )
        yield _counter("upcast_game_frames_late", "Frames started a period late", s.late_frames)
        yield _counter(
            "upcast_game_ring_timeouts", "Frames dropped: no ring R slot", s.ring_timeouts
        )
        yield _counter("upcast_game_render_errors", "Frames whose render failed", s.render_errors)
        yield _counter(
            "upcast_game_inputs_applied", "Player input events applied", s.inputs_applied
        )
        yield from ring_metrics([loop.ring])

    registry.register(_Snapshot(produce))
    return registry
