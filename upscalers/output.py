"""From an upscaler's tensor to the bytes of a display frame."""

from __future__ import annotations

import numpy as np
import torch


def quantize_into(image: torch.Tensor, out: np.ndarray) -> None:
    """Write a (3, H, W) upscaler result into an (H, W, 3) uint8 array (a ring U slot).

    uint8 results are copied as they are; float results are sRGB in [0, 1],
    non-finite values become 0, then round-to-nearest and clamp.
    """
    target = torch.from_numpy(out)
    if image.dtype == torch.uint8:
        target.copy_(image.permute(1, 2, 0))
        return
    x = torch.nan_to_num(image.float(), nan=0.0, posinf=1.0, neginf=0.0)
    target.copy_(x.mul(255.0).round_().clamp_(0.0, 255.0).permute(1, 2, 0))


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """A new (H, W, 3) uint8 array of the result (the in-process path)."""
    _, h, w = image.shape
    out = np.empty((h, w, 3), dtype=np.uint8)
    quantize_into(image, out)
    return out
