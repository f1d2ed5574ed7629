"""Texture reads from the cached frame at continuous pixel coordinates (centre i + 0.5)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def to_texture(color: torch.Tensor) -> torch.Tensor:
    """(H, W, C) -> the (1, C, H, W) layout ``bilinear`` reads."""
    return color.permute(2, 0, 1)[None].contiguous()


def bilinear(texture: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """(N, C) bilinear samples of a (1, C, H, W) texture at (N,) positions, edges clamped."""
    _, c, h, w = texture.shape
    grid = torch.stack((px * (2.0 / w) - 1.0, py * (2.0 / h) - 1.0), dim=-1).view(1, 1, -1, 2)
    out = F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out.view(c, -1).t()


def nearest_index(px: torch.Tensor, py: torch.Tensor, w: int, h: int) -> torch.Tensor:
    """Flat index of the pixel containing each position, clamped to the image."""
    # Truncation is floor once clamped to >= 0; floor(y) * W + x stays exact in float32
    # below 2^24 pixels, and truncating it adds floor(x).
    fy = py.clamp(0.0, h - 0.5).trunc_().mul_(float(w))
    return fy.add_(px.clamp(0.0, w - 0.5)).to(torch.int64)


def inside(px: torch.Tensor, py: torch.Tensor, w: int, h: int) -> torch.Tensor:
    return (px >= 0.0) & (px <= float(w)) & (py >= 0.0) & (py <= float(h))
