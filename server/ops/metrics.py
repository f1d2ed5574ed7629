"""Serving Prometheus metrics from a process (``--metrics-port``), and the pieces the
game's, the worker's and the rings' collectors share.

Most figures already exist as plain counters on ``GameStats``/``WorkerStats``, the
upscaler host and the rings' shared headers; the collectors (``server.game.metrics``,
``server.worker.metrics``, ``server.frames.metrics``) read them when Prometheus scrapes,
so the hot loops pay nothing but one histogram observation per frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, Metric
from prometheus_client.registry import Collector

log = logging.getLogger(__name__)

# Render and upscale times: 0.5 ms (tiny CPU frames) to 0.5 s (a stalled GPU).
STAGE_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2, 0.5)


class _Snapshot(Collector):
    """A collector built from a function that returns the metrics at scrape time."""

    def __init__(self, produce: Callable[[], Iterable[Metric]]) -> None:
        self._produce = produce

    def collect(self) -> Iterator[Metric]:
        yield from self._produce()


def _counter(name: str, doc: str, value: float) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, value=value)


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
