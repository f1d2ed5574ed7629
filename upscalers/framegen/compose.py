"""Predicted static background + the game's dynamic layer -> the frame to upscale.

The game draws only its moving objects for a predicted tick (colour, depth and
mask in a ring R slot flagged PREDICTED; the layer is not occluded by static
geometry). Here they go over the predicted background where they are nearer
than the background's predicted depth, which is the depth test the game would
have done had it drawn them into the predicted frame itself.
"""

from __future__ import annotations

import numpy as np

from server.frames.frame import RenderFrame
from upscalers.framegen.base import Prediction


def composite_dynamic(prediction: Prediction, layer: RenderFrame) -> RenderFrame:
    """A new frame: ``prediction`` with ``layer``'s dynamic pixels drawn over it.

    Motion is zero (the frame has no rendered predecessor of its own) and the
    mask marks the dynamic pixels that won the depth test. Non-finite layer
    depth counts as far, so a corrupt layer never punches through.
    """
    if prediction.color.shape != layer.color.shape:
        raise ValueError(
            f"dynamic layer is {layer.size} but the prediction is "
            f"{prediction.color.shape[1]}x{prediction.color.shape[0]}"
        )
    layer_depth = np.nan_to_num(layer.depth, nan=1.0, posinf=1.0, neginf=1.0)
    drawn = (layer.dynamic_mask != 0) & (layer_depth <= prediction.depth)
    color = np.where(drawn[..., None], layer.color, prediction.color)
    depth = np.where(drawn, layer_depth, prediction.depth).astype(np.float32, copy=False)
    h, w = depth.shape
    return RenderFrame(
        color=color,
        depth=depth,
        motion=np.zeros((h, w, 2), np.float32),
        dynamic_mask=drawn.astype(np.uint8),
        meta=layer.meta,
    )
