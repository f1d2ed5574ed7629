"""Prometheus metrics of the game and worker processes (``--metrics-port``).

Most figures already exist as plain counters on ``GameStats``/``WorkerStats``, the
upscaler host and the rings' shared headers; the collectors here read them when
Prometheus scrapes, so the hot loops pay nothing but one histogram observation per
frame. Names are listed in ``GAME_METRICS``/``WORKER_METRICS`` (the Grafana
dashboard test checks its queries against them).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Histogram, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from server.frames.ring import FrameRing

if TYPE_CHECKING:
    from server.game.loop import GameLoop
    from server.worker.upscale import UpscaleWorker

log = logging.getLogger(__name__)

# Render and upscale times: 0.5 ms (tiny CPU frames) to 0.5 s (a stalled GPU).
STAGE_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2, 0.5)

RING_FRAMES = "upcast_ring_frames"
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
WORKER_METRICS = (
    "upcast_worker_frames_upscaled",
    "upcast_worker_frames_dropped",
    "upcast_worker_frames_sanitized",
    "upcast_worker_values_sanitized",
    "upcast_worker_control_messages",
    "upcast_worker_upscaler_switches",
    "upcast_worker_upscaler",
    "upcast_worker_upscale_seconds",
    RING_FRAMES,
)


class _Snapshot(Collector):
    """A collector built from a function that returns the metrics at scrape time."""

    def __init__(self, produce: Callable[[], Iterable[Metric]]) -> None:
        self._produce = produce

    def collect(self) -> Iterator[Metric]:
        yield from self._produce()


def _counter(name: str, doc: str, value: float) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, value=value)


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


def worker_registry(worker: UpscaleWorker) -> CollectorRegistry:
    """A registry with the worker's metrics; also sets its upscale-time hook."""
    registry = CollectorRegistry()
    ProcessCollector(registry=registry)
    upscale = Histogram(
        "upcast_worker_upscale_seconds",
        "Time to upscale one frame (upscale_start -> output ready, quantizing included)",
        buckets=STAGE_BUCKETS,
        registry=registry,
    )
    worker.on_upscale_time = upscale.observe

    def produce() -> Iterator[Metric]:
        s, host = worker.stats, worker.host
        yield _counter("upcast_worker_frames_upscaled", "Frames upscaled into ring U", s.frames)
        dropped = CounterMetricFamily(
            "upcast_worker_frames_dropped",
            "Frames not presented (upscale_error, ring_u_full, truncated in ring R, "
            "prediction_refused: a predicted tick with no full render to predict from, "
            "prediction_error, prediction_warming: the predictor was still compiling)",
            labels=["reason"],
        )
        dropped.add_metric(["upscale_error"], s.errors)
        dropped.add_metric(["ring_u_full"], s.output_drops)
        dropped.add_metric(["truncated"], worker.ring_in.counters().rejected)
        pred = worker.prediction.stats
        dropped.add_metric(["prediction_refused"], pred.refused)
        dropped.add_metric(["prediction_error"], pred.errors)
        dropped.add_metric(["prediction_warming"], pred.warming)
        yield dropped
        yield _counter(
            "upcast_worker_frames_predicted",
            "Predicted frames (frame generation) presented into ring U; included in upscaled",
            pred.predicted,
        )
        yield _counter(
            "upcast_worker_frames_sanitized",
            "Frames with NaN/Inf G-buffer or camera values replaced",
            host.sanitized_frames,
        )
        yield _counter(
            "upcast_worker_values_sanitized", "NaN/Inf values replaced", host.sanitized_values
        )
        control = CounterMetricFamily(
            "upcast_worker_control_messages", "Control messages by result", labels=["result"]
        )
        control.add_metric(["ok"], s.control_messages - s.control_refused)
        control.add_metric(["refused"], s.control_refused)
        yield control
        yield _counter("upcast_worker_upscaler_switches", "Upscaler switches", s.switches)
        current = GaugeMetricFamily(
            "upcast_worker_upscaler", "The upscaler in use (value 1)", labels=["upscaler"]
        )
        current.add_metric([host.name], 1)
        yield current
        yield from ring_metrics([worker.ring_in, worker.ring_out])

    registry.register(_Snapshot(produce))
    return registry


def serve_metrics(registry: CollectorRegistry, port: int, what: str) -> None:
    """Expose ``registry`` on ``port`` (0: off) at ``/metrics`` in a daemon thread."""
    if not port:
        return
    try:
        start_http_server(port, registry=registry)
    except OSError as exc:  # a taken port costs the metrics, never the game or the worker
        log.warning("%s metrics port %d unavailable: %s", what, port, exc)
        return
    log.info("%s metrics on http://0.0.0.0:%d/metrics", what, port)
