"""The U-Net++ (nested skip paths), with the cache points of the paper's A.3.

Nodes X^{i,j} (depth i, position j along the skip path), n = 3:

    X00 ---------------- X01 ------- X02 ------- X03 -> residual
      \\                 /           /           /
      X10 ------- X11 ------- X12 --+
        \\        /           /
        X20 ------ X21 -----+
          \\      /
          X30 --+

X^{i,j} = conv(cat(X^{i,0}, ..., X^{i,j-1}, up(X^{i+1,j-1}))). The foundational
U-Net is X00, X10, X20, X30, X21, X12, X03; the nested extras are X01, X11, X02.

Module layout (so each cache point is one submodule the parent calls once):
``x00``, ``deep`` (everything at depth >= 1: X10, X20, X30, X21, X11 as
``deep.node11``, X12; returns cat(X10, X11, X12)), then the top row ``node01``,
``node02``, ``node03``.

Cache configs (our reading of A.3 / Figure 12):
- "B": ``deep``. The paper's choice ("cache the branches that lead into all the
  higher-level blocks X^{0,j}"): on a cached frame only the full-resolution row
  runs (X00, X01, X02, X03) on the cached depth-1 features. Most FLOPs removed.
- "A": ``node01``, ``node02``, ``deep.node11``: every nested extra node is reused,
  only the foundational U-Net blocks run. Fewer FLOPs removed, fresher output.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import nn

from upscalers.neural.blocks import ConcatConv, Up, conv3

DEFAULT_WIDTHS = (12, 32, 48, 64)


class _UpNode(nn.Module):
    """X^{i,j}: concatenates the same-depth inputs with the upsampled deeper one."""

    def __init__(self, same: int, deeper: int, cout: int, *, act: bool = True) -> None:
        super().__init__()
        self.up = Up(deeper, cout)
        self.conv = ConcatConv(conv3(same + cout, cout, act=act))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        *same, deeper = inputs
        return self.conv(*same, self.up(deeper))  # type: ignore[no-any-return]


class _Deep(nn.Module):
    """Every node at depth >= 1; returns cat(X10, X11, X12) at half resolution."""

    def __init__(self, widths: Sequence[int]) -> None:
        super().__init__()
        c0, c1, c2, c3 = widths
        self.node10 = nn.Sequential(conv3(c0, c1, stride=2), conv3(c1, c1))
        self.node20 = nn.Sequential(conv3(c1, c2, stride=2), conv3(c2, c2))
        self.node30 = nn.Sequential(conv3(c2, c3, stride=2), conv3(c3, c3), conv3(c3, c3))
        self.node21 = _UpNode(c2, c3, c2)
        self.node11 = _UpNode(c1, c2, c1)
        self.node12 = _UpNode(2 * c1, c2, c1)

    def forward(self, x00: torch.Tensor) -> torch.Tensor:
        x10 = self.node10(x00)
        x20 = self.node20(x10)
        x30 = self.node30(x20)
        x21 = self.node21(x20, x30)
        x11 = self.node11(x10, x20)
        x12 = self.node12(x10, x11, x21)
        return torch.cat((x10, x11, x12), 1)


class UNetPlusPlus(nn.Module):
    """Features (1, C, h, w) -> residual (1, out, h, w); h and w multiples of ``multiple``."""

    cache_configs: ClassVar[dict[str, tuple[str, ...]]] = {
        "A": ("node01", "node02", "deep.node11"),
        "B": ("deep",),
    }
    default_cache_config: ClassVar[str] = "B"

    def __init__(
        self, in_channels: int, out_channels: int, widths: Sequence[int] = DEFAULT_WIDTHS
    ) -> None:
        super().__init__()
        if len(widths) != 4:
            raise ValueError(f"the U-Net++ has 4 depths (X00..X30), got widths {widths}")
        self.widths = tuple(widths)
        self.multiple = 2 ** (len(widths) - 1)
        c0, c1 = widths[0], widths[1]
        self.c1 = c1
        self.x00 = conv3(in_channels, c0)
        self.deep = _Deep(widths)
        self.node01 = _UpNode(c0, c1, c0)
        self.node02 = _UpNode(2 * c0, c1, c0)
        self.node03 = _UpNode(3 * c0, c1, c0)
        self.out = nn.Conv2d(c0, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x00 = self.x00(x)
        x10, x11, x12 = torch.split(self.deep(x00), self.c1, 1)
        x01 = self.node01(x00, x10)
        x02 = self.node02(x00, x01, x11)
        x03 = self.node03(x00, x01, x02, x12)
        return self.out(x03)  # type: ignore[no-any-return]
