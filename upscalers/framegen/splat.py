"""``splat``: per-pixel forward reprojection, the baseline the paper rejects (cracks, overlaps).

Every static cached pixel is unprojected with its depth (sky as a direction),
reprojected into the new camera and written to the pixel it lands in; a
z-buffer keeps the nearest (one ``scatter_reduce(amin)`` over the packed key
(depth bits << 31) | source index, as in ``raster.py``). Pixels nothing lands
on are holes (cracks where the surface magnifies, disocclusions, the screen
edge) and get the shared pull-push fill.
"""

from __future__ import annotations

import torch

from upscalers.framegen.base import CachedFrame, FramePredictor, Prediction, to_prediction
from upscalers.framegen.fill import pull_push_fill
from upscalers.framegen.geometry import Reprojection, reproject_points, sky_as_direction
from upscalers.framegen.raster import KEY_NONE, TRI_BITS


class SplatPredictor(FramePredictor):
    name = "splat"

    def _predict(self, cache: CachedFrame, reproj: Reprojection) -> Prediction:
        w, h = cache.size
        dev = self.device
        n = w * h
        pix = torch.arange(n, device=dev)
        px = (pix % w).to(torch.float32) + 0.5
        py = torch.div(pix, w, rounding_mode="floor").to(torch.float32) + 0.5
        depth = sky_as_direction(cache.depth, reproj.cached_z_inf).view(-1)
        p = reproject_points(reproj.tensor("forward", dev), px, py, depth, w, h)
        tx, ty = p.px.floor(), p.py.floor()
        ok = p.valid & ~cache.dynamic.view(-1) & (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
        dst = torch.where(ok, ty * w + tx, torch.zeros_like(tx)).to(torch.int64)
        zbits = p.depth.clamp_min(0.0).view(torch.int32).to(torch.int64)
        key = torch.where(ok, (zbits << TRI_BITS) | pix, torch.full_like(zbits, KEY_NONE))
        zbuf = torch.full((n,), KEY_NONE, dtype=torch.int64, device=dev)
        zbuf.scatter_reduce_(0, dst, key, reduce="amin", include_self=True)
        hit = zbuf != KEY_NONE
        src = torch.where(hit, zbuf & ((1 << TRI_BITS) - 1), torch.zeros_like(zbuf))
        color = cache.color.view(-1, 3)[src]
        out_depth = torch.where(hit, p.depth[src].clamp(0.0, 1.0), torch.ones_like(p.depth))
        holes = ~hit.view(h, w)
        color = pull_push_fill(color.view(h, w, 3), holes)
        return to_prediction(color, holes, out_depth.view(h, w), cache.frame_id, holes)
