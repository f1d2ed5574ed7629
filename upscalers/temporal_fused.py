"""The render-size stage of the temporal upscaler as one pure function, for ``torch.compile``.

Same math as ``TemporalUpscaler._render_stage`` for a frame with history: the
eager version is ~40 small kernels (pads, 3x3 min/max, closest-depth selects,
the reprojection test, takes), each a pass over render-size planes, which
inductor fuses into a couple of loops.

The display-size blend is not compiled: written per display pixel (render-size
values and samples read through index tables, history through grid_sample),
inductor's loops gather instead of streaming; a whole frame compiled that way
measured slower than eager (1 thread, 640x360 -> 1280x720, interleaved in one
run on a shared machine: 279 ms against 164 ms), where the eager planar layout
of ``temporal.py`` streams long contiguous rows.
"""

from __future__ import annotations

import torch

from upscalers import temporal_ops as ops


def render_stage(
    color: torch.Tensor,
    depth: torch.Tensor,
    motion: torch.Tensor,
    mask: torch.Tensor,
    prev_far: torch.Tensor,
    weight_state: torch.Tensor,
    jit: torch.Tensor,
    prev_jit: torch.Tensor,
    near_far: torch.Tensor,
    params: tuple[float, float, float, float],
) -> tuple[torch.Tensor, ...]:
    """The render-size half of a frame with history (see TemporalUpscaler.upscale and
    _reproject_weight): YCoCg samples, their 3x3 box, the trusted accumulated weight
    at the reprojected position, the dilated motion and this frame's 2x2 max depth."""
    presharpen, depth_tolerance, dynamic_keep, max_weight = params
    h, w = depth.shape
    ycocg = ops.rgb8_to_ycocg(color, torch.float32)
    if presharpen > 0.0:
        ycocg = ops.sharpen(ycocg, presharpen)
    lo, hi = ops.box_3x3(ycocg)
    depth = torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    lim = 4.0 * max(w, h)
    motion = torch.nan_to_num(motion, nan=0.0, posinf=0.0, neginf=0.0).clamp(-lim, lim)
    near, far = near_far[0], near_far[1]
    lin = torch.reciprocal(depth * (-(far - near) / (near * far)) + 1.0 / near)
    # An empty mask dilates to zeros and leaves the trust unchanged: no branch needed.
    mask_d = ops.box_3x3(mask.to(torch.float32).unsqueeze(0))[1][0]
    lin_d, mv = ops.closest_3x3(lin, motion.permute(2, 0, 1))
    xs = torch.arange(w, device=depth.device, dtype=torch.float32) + 0.5 + jit[0]
    ys = torch.arange(h, device=depth.device, dtype=torch.float32) + 0.5 + jit[1]
    qx = mv[0] + xs
    qy = mv[1] + ys.unsqueeze(1)
    inside = (qx >= 0.0) & (qx <= w) & (qy >= 0.0) & (qy <= h)
    kx = (qx - (0.5 + prev_jit[0])).floor().clamp(0, w - 1).long()
    ky = (qy - (0.5 + prev_jit[1])).floor().clamp(0, h - 1).long()
    idx = ky * w + kx
    farthest = prev_far.reshape(-1)[idx] * (1.0 + depth_tolerance)
    trust = (inside & (farthest >= lin_d)).to(torch.float32)
    trust = trust * (mask_d * (dynamic_keep - 1.0) + 1.0)
    weight = torch.nan_to_num(weight_state.reshape(-1)[idx], nan=0.0, posinf=0.0)
    prev_weight = weight.clamp(0.0, max_weight) * trust
    return ycocg, lo, hi, prev_weight, mv, ops.max_2x2(lin)
