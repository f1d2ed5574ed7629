"""The U-Net, written recursively so layer caching needs no edit of its forward.

``UNetLevel(enc, inner, dec)`` computes ``dec(cat(e, inner(e)))`` with
``e = enc(x)``; ``inner`` is the whole next level (stride-2 downsampling, the
deeper levels, upsampling back) as ONE submodule. Skipping ``inner`` therefore
skips every layer below it, which is what ``upscalers/cache`` does on a cached
frame: cache level 1 keeps the output of ``body.inner`` (the paper's "cache the
last block": only the full-resolution encoder and decoder run), level 2 of
``body.inner.inner``, level 3 of the deepest one.

Channels grow with depth (12, 32, 48, 64 by default) and the top level is thin,
so most of the work sits below the first cache point: on a 640x360 input the
top level is about a third of the multiply-adds (``flops.conv_flops``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import nn

from upscalers.neural.blocks import Up, conv3

DEFAULT_WIDTHS = (12, 32, 48, 64)


class UNetLevel(nn.Module):
    def __init__(self, enc: nn.Module, inner: nn.Module, dec: nn.Module) -> None:
        super().__init__()
        self.enc = enc
        self.inner = inner
        self.dec = dec

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = self.enc(x)
        return self.dec(torch.cat((e, self.inner(e)), 1))  # type: ignore[no-any-return]


def _level(widths: Sequence[int], depth: int) -> nn.Module:
    """Level ``depth`` >= 1 as one module: input and output have widths[depth - 1]
    channels at twice its resolution."""
    c_in, c = widths[depth - 1], widths[depth]
    if depth == len(widths) - 1:
        return nn.Sequential(conv3(c_in, c, stride=2), conv3(c, c), conv3(c, c), Up(c, c_in))
    enc = nn.Sequential(conv3(c_in, c, stride=2), conv3(c, c))
    dec = nn.Sequential(conv3(2 * c, c), Up(c, c_in))
    return UNetLevel(enc, _level(widths, depth + 1), dec)


class UNet(nn.Module):
    """Features (1, C, h, w) -> residual (1, out, h, w); h and w multiples of ``multiple``."""

    cache_configs: ClassVar[dict[str, tuple[str, ...]]] = {
        "1": ("body.inner",),
        "2": ("body.inner.inner",),
        "3": ("body.inner.inner.inner",),
    }
    default_cache_config: ClassVar[str] = "1"

    def __init__(
        self, in_channels: int, out_channels: int, widths: Sequence[int] = DEFAULT_WIDTHS
    ) -> None:
        super().__init__()
        if len(widths) != 4:
            raise ValueError(f"the U-Net has 4 levels (cache levels 1-3), got widths {widths}")
        self.widths = tuple(widths)
        self.multiple = 2 ** (len(widths) - 1)
        top = widths[0]
        self.body = UNetLevel(
            conv3(in_channels, top),
            _level(widths, 1),
            nn.Sequential(conv3(2 * top, 16), nn.Conv2d(16, out_channels, 1)),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)  # type: ignore[no-any-return]
