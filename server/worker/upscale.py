"""The decoupled upscaler worker: ring R -> upscaler -> ring U, in its own process.

It needs nothing of the game but the ring names: it attaches to ring R as the
consumer and ring U as the producer, and takes run-time control messages on a
Unix socket. A frame that makes the upscaler fail is logged and skipped; the
worker keeps going.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from server.config_types import CachePolicyName, PredictorName, SizeText, UpscalerName
from server.frames.frame import FrameFlags
from server.frames.ring import FrameRing
from server.frames.ring_frames import (
    render_frame_of,
    write_meta,
)
from server.frames.timing import Stage, stamp
from server.worker.control import (
    ControlServer,
    GetStatus,
    SetCachePolicy,
    SetUpscaler,
    parse_message,
)
from server.worker.prediction import PredictionStage
from upscalers import framegen, registry
from upscalers.host import UpscalerHost, color_only_methods
from upscalers.output import quantize_into

log = logging.getLogger(__name__)


class WorkerConfig(BaseModel):
    """Worker settings, validated at start."""

    model_config = ConfigDict(extra="forbid")

    ring_in: str = Field(description="name of ring R (G-buffers) to consume")
    ring_out: str = Field(description="name of ring U (display frames) to produce")
    upscaler: UpscalerName = Field(default="bilinear", description="upscaler to start with")
    display_size: SizeText = Field(default="1280x720", description="output size WIDTHxHEIGHT")
    control_path: Path | None = Field(default=None, description="Unix socket for control")
    threads: int = Field(
        default=1, ge=1, le=256, description="CPU threads for torch and for numba's kernels"
    )
    attach_timeout_s: float = Field(default=10.0, ge=0, description="wait for the rings")
    newest: bool = Field(default=False, description="skip to the newest frame when behind")
    metrics_port: int = Field(
        default=0, ge=0, le=65535, description="Prometheus /metrics TCP port (0: off)"
    )
    predictor: PredictorName = Field(
        default="mpe",
        description="frame predictor for the game's PREDICTED ticks (frame generation): "
        + ", ".join(framegen.available()),
    )
    cache_policy: CachePolicyName | None = Field(
        default=None,
        description="layer-cache policy of the methods with a cache (unet_cached): "
        "delta_l, delta_h, budget, every_N, deepcache, motion, NAME@VALUE (None: their default)",
    )
    compile: bool = Field(
        default=False,
        description="torch.compile the upscalers that have a compiled path (first frame "
        "of a size waits for the compile; inductor's disk cache makes later starts fast); "
        "on the CPU the default numba kernels are faster, so this is for CUDA",
    )


@dataclass
class WorkerStats:
    # frames: every frame presented into ring U, rendered or predicted.
    frames: int = 0
    errors: int = 0
    output_drops: int = 0
    switches: int = 0
    control_messages: int = 0
    control_refused: int = 0


class UpscaleWorker:
    """The loop body, separated from process concerns so tests can drive it."""

    def __init__(
        self,
        ring_in: FrameRing,
        ring_out: FrameRing,
        host: UpscalerHost,
        *,
        newest: bool = False,
        prediction: PredictionStage | None = None,
    ) -> None:
        ring_out.require_fits(*host.display_size, what="display size")
        # Turns the game's PREDICTED ticks (only moving objects drawn) into whole frames.
        self.prediction = prediction or PredictionStage(background=True)
        self.ring_in = ring_in
        self.ring_out = ring_out
        self.host = host
        self.newest = newest
        self.stats = WorkerStats()
        # Seconds per upscale, for the --metrics-port histogram (server/worker/metrics.py).
        self.on_upscale_time: Callable[[float], None] | None = None
        ring_in.attach_as_consumer()
        ring_out.attach_as_producer()

    def process_next(self, timeout_s: float) -> bool:
        """Upscale one frame if one arrives within ``timeout_s``; False if none came."""
        lease = self.ring_in.acquire_read(timeout_s, newest=self.newest)
        if lease is None:
            return False
        with lease:
            frame = render_frame_of(lease)
            meta = frame.meta
            stamp(meta.stamps, Stage.UPSCALE_START)
            if meta.flags & FrameFlags.PREDICTED:
                # upscale_start..end of a predicted frame spans prediction + composite + upscale.
                predicted = self.prediction.predict(frame)
                if predicted is None:
                    return True  # counted in prediction.stats; the stream skips the tick
                frame = predicted
            elif not meta.flags & FrameFlags.COLOR_ONLY:
                # A colour-only frame has no depth or motion to predict from.
                self.prediction.rendered(frame)
            try:
                result = self.host.upscale(frame)
            except Exception:
                self.stats.errors += 1
                log.exception(
                    "upscaler %s failed on frame %d; skipped", self.host.name, meta.frame_id
                )
                return True
        out = self.ring_out.acquire_write(timeout_s=0.5)
        if out is None:
            # Lossless ring U and nobody reading it: drop here rather than stall the game.
            self.stats.output_drops += 1
            return True
        with out:
            size = self.host.display_size
            views = out.views(size.width, size.height)
            quantize_into(result, views["color"])
            stamp(meta.stamps, Stage.UPSCALE_END)
            if self.on_upscale_time is not None:
                upscale_ns = meta.stamps[Stage.UPSCALE_END, 0] - meta.stamps[Stage.UPSCALE_START, 0]
                self.on_upscale_time(float(upscale_ns) / 1e9)
            write_meta(out.header, meta)
            out.commit(stamp_stage=Stage.RING_U_READY)
        self.stats.frames += 1
        return True

    def handle_control(self, server: ControlServer) -> None:
        for data, addr in server.poll():
            self.stats.control_messages += 1
            try:
                message = parse_message(data)
                if isinstance(message, SetUpscaler):
                    self.host.switch(message.name)
                    self.stats.switches += 1
                    reply = {"upscaler": self.host.name, "cache_policy": self.host.cache_policy}
                    server.reply(addr, {"ok": True, **reply})
                elif isinstance(message, SetCachePolicy):
                    self.host.set_cache_policy(message.policy)
                    server.reply(addr, {"ok": True, "cache_policy": self.host.cache_policy})
                elif isinstance(message, GetStatus):
                    server.reply(addr, {"ok": True, **self.status()})
            except ValueError as exc:
                self.stats.control_refused += 1
                log.warning("control message refused: %s", exc)
                server.reply(addr, {"ok": False, "error": str(exc)})

    def status(self) -> dict[str, Any]:
        return {
            "upscaler": self.host.name,
            "cache_policy": self.host.cache_policy,
            "display_size": str(self.host.display_size),
            # The source's frames carry colour only: the methods that work on them.
            "color_only": self.host.color_only,
            "upscalers": color_only_methods() if self.host.color_only else registry.available(),
            "frames": self.stats.frames,
            "errors": self.stats.errors,
            "output_drops": self.stats.output_drops,
            "switches": self.stats.switches,
            "predictor": self.prediction.predictor_name,
            "predicted": self.prediction.stats.predicted,
            "prediction_refused": self.prediction.stats.refused,
            "prediction_errors": self.prediction.stats.errors,
            "prediction_warming": self.prediction.stats.warming,
            "sanitized_values": self.host.sanitized_values,
            "sanitized_frames": self.host.sanitized_frames,
        }

    def progress(self, frames_before: int, interval_s: float) -> str:
        """One line for the periodic log: the method, the frame rate over the interval
        and the counters, without the status' lists (the control API has those)."""
        s, p = self.stats, self.prediction.stats
        fps = (s.frames - frames_before) / interval_s if interval_s > 0 else 0.0
        cache = f", cache {self.host.cache_policy}" if self.host.cache_policy else ""
        line = (
            f"{self.host.name}{cache} -> {self.host.display_size}: {fps:.1f} fps, "
            f"{s.frames} frames, {s.errors} errors, {s.output_drops} output drops, "
            f"{s.switches} switches"
        )
        if self.prediction.predictor_name is not None and p.predicted + p.refused + p.errors:
            line += f"; predicted {p.predicted}, refused {p.refused}, errors {p.errors}"
        if self.host.sanitized_frames:
            line += f"; {self.host.sanitized_frames} frames with NaN/Inf replaced"
        return line

    def run(self, stop: threading.Event, control: ControlServer | None = None) -> None:
        last_report = time.monotonic()
        frames_at_report = self.stats.frames
        while not stop.is_set():
            if control is not None:
                self.handle_control(control)
            self.process_next(timeout_s=0.1)
            now = time.monotonic()
            if now - last_report >= 10.0:
                log.info("worker: %s", self.progress(frames_at_report, now - last_report))
                last_report, frames_at_report = now, self.stats.frames
