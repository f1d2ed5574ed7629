"""The display-size half of the temporal upscaler as one pure function, for ``torch.compile``.

Same math as the eager integer-scale path of ``temporal.py`` (history fetch at
p + motion with the Catmull-Rom luma correction, clamp to the YCoCg box,
current-frame reconstruction from the jittered samples, confidence blend,
uint8 output), written per display pixel with render-size values read through
index tables instead of the planar layout. Eagerly that would be many full
display-size passes; the CPU profile of the eager path shows its time in
display-size copy/add/clamp/lerp/min/max kernels, which inductor fuses into a
few loops. The render-size half (box, dilated motion, trust) stays eager.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from upscalers import temporal_ops as ops

# block index, sample 0, sample 1, fraction, sample weight, grid coordinate
AxisTables = tuple[
    torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor
]

_YCOCG_TO_RGB = ((1.0, 1.0, -1.0), (1.0, 0.0, 1.0), (1.0, -1.0, -1.0))


def axis_tables(
    n_display: int, n_render: int, scale: int, jitter: float, k: float,
    sample_weight: torch.Tensor, dt: torch.dtype,
) -> AxisTables:  # fmt: skip
    """Per display index along one axis: its render block, the two render samples it
    lies between (clamped to the image: edges repeated), the sharpened fraction between
    them, this frame's sample weight (``sample_weight`` per sub-pixel) and the
    grid_sample coordinate of the pixel centre."""
    dev = sample_weight.device
    taps = ops.phase_taps(scale, jitter, k)
    index = torch.arange(n_display, device=dev)
    block, sub = index // scale, index % scale
    n = torch.tensor([t[0] for t in taps], device=dev)[sub]
    f = torch.tensor([t[1] for t in taps], device=dev, dtype=dt)[sub]
    i0 = (block + n).clamp_(0, n_render - 1)
    i1 = (block + n + 1).clamp_(0, n_render - 1)
    coord = index.to(dt).add_(0.5).mul_(2.0 / n_display).sub_(1.0)
    return block, i0, i1, f, sample_weight[sub], coord


def blend_blocked(
    history: torch.Tensor,
    ycocg: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    prev_weight: torch.Tensor,
    mv: torch.Tensor,
    rows: AxisTables,
    cols: AxisTables,
    scale: int,
    sharpen_gain: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """New (3, H, W) YCoCg history and the (H, W, 3) uint8 sRGB output.

    ``history`` (3, H, W); render-size ``ycocg``, ``lo``, ``hi`` (3, h, w),
    ``prev_weight`` (h, w), ``mv`` (2, h, w). ``rows`` / ``cols`` per display row /
    column: render block index, the two reconstruction samples, their fraction, the
    sample weight, and the grid_sample coordinate of the pixel centre (row tensors
    (H, 1), column tensors (1, W)).
    """
    _, big_h, big_w = history.shape
    h, w = prev_weight.shape
    rb, r0, r1, fy, wy, gy = rows
    cb, c0, c1, fx, wx, gx = cols
    mvx, mvy = mv[0][rb, cb], mv[1][rb, cb]
    grid = torch.stack((gx + mvx * (2.0 / w), gy + mvy * (2.0 / h)), -1)
    fetched = F.grid_sample(
        history[None], grid[None], mode="bilinear", padding_mode="border", align_corners=False
    )[0]
    fetched = torch.nan_to_num(fetched, nan=0.0, posinf=0.0, neginf=0.0)
    # Catmull-Rom correction of luma (see TemporalUpscaler._sharpen_fetch).
    tx = mvx * float(scale)
    tx = tx - tx.floor()
    ty = mvy * float(scale)
    ty = ty - ty.floor()
    cx = tx * (1.0 - tx) * (-0.5 * sharpen_gain)
    cy = ty * (1.0 - ty) * (-0.5 * sharpen_gain)
    luma = fetched[0]
    ys = torch.arange(big_h, device=history.device).view(-1, 1)
    xs = torch.arange(big_w, device=history.device).view(1, -1)
    left, right = luma[ys, (xs - 1).clamp_min(0)], luma[ys, (xs + 1).clamp_max(big_w - 1)]
    up, down = luma[(ys - 1).clamp_min(0), xs], luma[(ys + 1).clamp_max(big_h - 1), xs]
    luma = luma * (1.0 - 2.0 * (cx + cy)) + cx * (left + right) + cy * (up + down)
    prev = torch.cat((luma[None], fetched[1:]))
    prev = torch.minimum(torch.maximum(prev, lo[:, rb, cb]), hi[:, rb, cb])
    top = torch.lerp(ycocg[:, r0, c0], ycocg[:, r0, c1], fx)
    bottom = torch.lerp(ycocg[:, r1, c0], ycocg[:, r1, c1], fx)
    cur = torch.lerp(top, bottom, fy)
    weight = wy * wx
    alpha = weight / (prev_weight[rb, cb] + weight)
    new = torch.lerp(prev, cur, alpha)
    m = torch.tensor(_YCOCG_TO_RGB, device=new.device, dtype=new.dtype) * 255.0
    rgb = [(m[c, 0] * new[0] + m[c, 1] * new[1] + m[c, 2] * new[2] + 0.5) for c in range(3)]
    rgb8 = torch.stack(rgb, -1).clamp(0.0, 255.0).to(torch.uint8)
    return new, rgb8
