"""Prometheus metrics of the worker process (``--metrics-port``). Names are listed in
``WORKER_METRICS`` (the Grafana dashboard test checks its queries against them)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.process_collector import ProcessCollector

from server.frames.metrics import RING_FRAMES, ring_metrics
from server.ops.metrics import STAGE_BUCKETS, _counter, _Snapshot

if TYPE_CHECKING:
    from server.worker.upscale import UpscaleWorker

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
