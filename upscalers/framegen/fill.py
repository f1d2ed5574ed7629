"""Hole filling by pull-push: a plausible colour for pixels without a source.

Holes are averaged in from the surrounding valid pixels through an image
pyramid (Gortler et al.'s pull-push), so a hole takes the blurred colour of
its rim. Every predictor fills the same way; the hole mask still says which
pixels were guessed.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def pull_push_fill(values: torch.Tensor, holes: torch.Tensor) -> torch.Tensor:
    """(H, W, C) values with ``holes`` (H, W) replaced from their neighbourhood."""
    if not bool(holes.any()):
        return values
    if bool(holes.all()):
        return torch.zeros_like(values)
    weight = (~holes).to(values.dtype)[None, None]
    img = values.permute(2, 0, 1)[None] * weight
    levels: list[tuple[torch.Tensor, torch.Tensor]] = []
    while max(img.shape[-2:]) > 1:
        levels.append((img, weight))
        h, w = img.shape[-2:]
        pad = (0, w % 2, 0, h % 2)  # zero weight outside, so sums stay exact
        # Sums over 2x2 blocks; colour stays premultiplied by a weight clamped to 1.
        s_img = F.avg_pool2d(F.pad(img, pad), 2) * 4.0
        s_w = F.avg_pool2d(F.pad(weight, pad), 2) * 4.0
        img = s_img / s_w.clamp_min(1.0)
        weight = s_w.clamp_max(1.0)
    filled = img / weight.clamp_min(1e-6)
    for img_l, w_l in reversed(levels):
        h, w = img_l.shape[-2:]
        up = filled.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3)[..., :h, :w]
        filled = img_l + up * (1.0 - w_l)  # img_l is premultiplied by w_l
    out = filled[0].permute(1, 2, 0)
    return torch.where(holes[..., None], out, values)
