"""The worker process: attach to the rings, serve the metrics and the control socket,
upscale until stopped."""

from __future__ import annotations

import logging
import signal
import threading

from server.frames.frame import Size
from server.frames.ring_frames import attach_display_ring, attach_render_ring
from server.ops.cpu_threads import set_cpu_threads
from server.ops.metrics import serve_metrics
from server.worker.control import ControlServer
from server.worker.metrics import worker_registry
from server.worker.prediction import PredictionStage
from server.worker.upscale import UpscaleWorker, WorkerConfig
from upscalers.host import UpscalerHost

log = logging.getLogger(__name__)


def run_worker(config: WorkerConfig, stop: threading.Event | None = None) -> int:
    """Attach to the rings and upscale until stopped (SIGTERM/SIGINT)."""
    # Set here, on the thread that upscales and predicts: numba's limit is per thread.
    set_cpu_threads(config.threads)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    ring_in = attach_render_ring(config.ring_in, wait_s=config.attach_timeout_s)
    ring_out = attach_display_ring(config.ring_out, wait_s=config.attach_timeout_s)
    host = UpscalerHost(
        config.upscaler,
        Size.parse(config.display_size),
        compile=config.compile,
        cache_policy=config.cache_policy,
    )
    prediction = PredictionStage(config.predictor, background=True)
    worker = UpscaleWorker(ring_in, ring_out, host, newest=config.newest, prediction=prediction)
    serve_metrics(worker_registry(worker), config.metrics_port, "worker")
    control = ControlServer(config.control_path) if config.control_path else None
    log.info(
        "worker up: %s -> %s (%s, %s), control %s",
        config.ring_in,
        config.ring_out,
        config.upscaler,
        config.display_size,
        config.control_path,
    )
    try:
        worker.run(stop, control)
    finally:
        log.info("worker stopping: %s", worker.status())
        if control is not None:
            control.close()
        ring_in.close()
        ring_out.close()
    return 0
