"""The worker's frame-generation stage: PREDICTED slots of ring R become whole frames.

With frame generation on, the game alternates full renders with ticks where it
draws only its moving objects (flag PREDICTED). For such a tick this stage
predicts the static background from the last full render with the configured
predictor (MPE by default) toward the tick's camera, and composites the
game's dynamic layer over it; the worker then upscales and presents it like
any frame, still flagged PREDICTED.

Rendered frames are only copied here (a memcpy of colour, depth and mask);
the predictor observes the copy when the next predicted tick arrives, so a
session without frame generation pays nothing but the copy, and the
observe cost is counted where it belongs, on the predicted frame.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from server.frames.frame import FrameFlags, RenderFrame
from upscalers import framegen
from upscalers.framegen.compose import composite_dynamic

log = logging.getLogger(__name__)


@dataclass
class PredictionStats:
    predicted: int = 0  # predicted frames handed on to the upscaler
    refused: int = 0  # predicted ticks with nothing to predict from (no full render yet, a cut)
    warming: int = 0  # predicted ticks that came while the predictor was still compiling
    errors: int = 0  # predicted ticks whose prediction raised


def _copy_frame(frame: RenderFrame, into: RenderFrame | None) -> RenderFrame:
    """A private copy of ``frame`` (reusing ``into``'s buffers when the size matches)."""
    if into is None or into.size != frame.size:
        return RenderFrame(
            frame.color.copy(),
            frame.depth.copy(),
            np.zeros_like(frame.motion),  # predictors here never read motion
            frame.dynamic_mask.copy(),
            frame.meta,
        )
    np.copyto(into.color, frame.color)
    np.copyto(into.depth, frame.depth)
    np.copyto(into.dynamic_mask, frame.dynamic_mask)
    return RenderFrame(into.color, into.depth, into.motion, into.dynamic_mask, frame.meta)


class PredictionStage:
    """``background=True`` builds the predictor on a thread: MPE's CPU kernels compile on
    first use (about 18 s with an empty numba cache, under 1 s from it), and neither
    the worker's start nor a session without frame generation should wait for that.
    Predicted ticks that arrive meanwhile are skipped (``stats.warming``)."""

    def __init__(
        self,
        predictor: str = "mpe",
        device: str | torch.device = "cpu",
        *,
        background: bool = False,
    ) -> None:
        if predictor not in framegen.available():
            raise ValueError(
                f"unknown frame predictor {predictor!r}; allowed: {', '.join(framegen.available())}"
            )
        self.predictor_name = predictor
        self.stats = PredictionStats()
        self._predictor: framegen.FramePredictor | None = None
        self._ready = threading.Event()
        self._last_rendered: RenderFrame | None = None
        self._observed_id: int | None = None
        if background:
            threading.Thread(
                target=self._build, args=(device,), name="predictor-warm-up", daemon=True
            ).start()
        else:
            self._build(device)

    def _build(self, device: str | torch.device) -> None:
        start = time.monotonic()
        try:
            self._predictor = framegen.create(self.predictor_name, device)
        except Exception:
            log.exception("frame predictor %s could not be built", self.predictor_name)
            return
        self._ready.set()
        log.info(
            "frame predictor %s ready in %.1f s", self.predictor_name, time.monotonic() - start
        )

    def wait_ready(self, timeout_s: float | None = None) -> bool:
        return self._ready.wait(timeout_s)

    def rendered(self, frame: RenderFrame) -> None:
        """Keep the latest full render (call while its ring slot is still held)."""
        self._last_rendered = _copy_frame(frame, self._last_rendered)
        self._observed_id = None

    def predict(self, layer: RenderFrame) -> RenderFrame | None:
        """The frame for a PREDICTED tick, or None when it cannot be predicted."""
        predictor = self._predictor
        if predictor is None:
            self.stats.warming += 1
            return None
        source = self._last_rendered
        if source is None or source.size != layer.size:  # nothing yet, or the scale changed
            self.stats.refused += 1
            return None
        try:
            if self._observed_id != source.meta.frame_id:
                predictor.observe(source)
                self._observed_id = source.meta.frame_id
            cam = layer.meta.camera
            # RESET on the tick means a cut lies between it and the source: never predict across.
            prediction = predictor.predict(cam.view, cam.proj, layer.meta.flags)
            if prediction is None:
                self.stats.refused += 1
                return None
            frame = composite_dynamic(prediction, layer)
        except Exception:
            self.stats.errors += 1
            log.exception("prediction of frame %d failed; skipped", layer.meta.frame_id)
            return None
        frame.meta.flags |= FrameFlags.PREDICTED
        self.stats.predicted += 1
        return frame
