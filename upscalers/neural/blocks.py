"""Building blocks shared by the U-Net and the U-Net++: 3x3 convolutions with a leaky
ReLU, stride-2 downsampling, and upsampling that reduces channels before it grows
the image (a 1x1 convolution at the low resolution, then bilinear x2), which is
the cheap order on a CPU."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

NEGATIVE_SLOPE = 0.1


def conv3(cin: int, cout: int, *, stride: int = 1, act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, 3, stride=stride, padding=1)]
    if act:
        layers.append(nn.LeakyReLU(NEGATIVE_SLOPE))
    return nn.Sequential(*layers)


class Up(nn.Module):
    """1x1 convolution to ``cout`` channels, then bilinear x2."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(self.proj(x), scale_factor=2.0, mode="bilinear", align_corners=False)


class ConcatConv(nn.Module):
    """A node that concatenates its inputs along channels and applies a block."""

    def __init__(self, block: nn.Module) -> None:
        super().__init__()
        self.block = block

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.block(torch.cat(inputs, 1))  # type: ignore[no-any-return]
