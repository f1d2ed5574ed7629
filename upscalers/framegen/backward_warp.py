"""``backward_warp``: warp by the cached frame's own motion vectors, the cheap baseline.

The new frame's true mapping (new pixel -> cached pixel) needs the new
frame's motion, which does not exist yet. This baseline approximates it by
the cached frame's motion at the same pixel, scaled to the prediction
interval: new pixel q reads the cached colour at ``q + motion_scale * mv(q)``
(``mv`` points from the cached frame to the frame rendered before it, so a
constant-velocity extrapolation flips nothing: the content at q moved by
``-mv`` per rendered interval). ``motion_scale`` is the predicted interval
over the rendered one: 0.5 when each rendered frame is followed by one
predicted frame at twice the rate. It ignores the new camera entirely: wrong
at depth edges, wrong when the camera accelerates, nothing for disocclusion.
"""

from __future__ import annotations

import torch

from upscalers.framegen.base import CachedFrame, FramePredictor, Prediction, to_prediction
from upscalers.framegen.fill import pull_push_fill
from upscalers.framegen.geometry import Reprojection
from upscalers.framegen.sample import bilinear, inside, nearest_index, to_texture


class BackwardWarpPredictor(FramePredictor):
    name = "backward_warp"

    def __init__(self, motion_scale: float = 0.5, device: str | torch.device | None = None) -> None:
        super().__init__(device)
        self.motion_scale = motion_scale

    def _predict(self, cache: CachedFrame, reproj: Reprojection) -> Prediction:
        w, h = cache.size
        dev = self.device
        pix = torch.arange(w * h, device=dev)
        mv = cache.motion.view(-1, 2)
        u = (pix % w).to(torch.float32) + 0.5 + self.motion_scale * mv[:, 0]
        v = torch.div(pix, w, rounding_mode="floor").to(torch.float32) + 0.5
        v = v + self.motion_scale * mv[:, 1]
        src = nearest_index(u, v, w, h)
        dyn = cache.dynamic.view(-1)[src]
        holes = (dyn | ~inside(u, v, w, h)).view(h, w)
        color = bilinear(to_texture(cache.color), u, v).view(h, w, 3)
        color = pull_push_fill(color, dyn.view(h, w))
        depth = cache.depth.view(-1)[src].view(h, w)
        return to_prediction(color, holes, depth, cache.frame_id, dyn.view(h, w))
