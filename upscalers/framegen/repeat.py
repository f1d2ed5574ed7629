"""``repeat``: show the cached frame again (what a display does without prediction)."""

from __future__ import annotations

import torch

from upscalers.framegen.base import CachedFrame, FramePredictor, Prediction, to_prediction
from upscalers.framegen.geometry import Reprojection


class RepeatPredictor(FramePredictor):
    name = "repeat"

    def _predict(self, cache: CachedFrame, reproj: Reprojection) -> Prediction:
        holes = torch.zeros_like(cache.dynamic)
        return to_prediction(cache.color, holes, cache.depth, cache.frame_id)
