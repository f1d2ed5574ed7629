"""Separable Lanczos-2 resampling: the classic windowed-sinc baseline.

Same geometry as torch's ``align_corners=False``: output pixel ``o`` samples the
input at ``(o + 0.5) * in / out - 0.5``, texels outside the image repeat the edge.
The kernel is ``sinc(x) sinc(x / 2)`` on ``|x| < 2``, widened by ``in / out`` when
downscaling (antialiasing); each output's weights are normalized to sum to 1.
The result is clamped to [0, 1] (the negative lobes overshoot at edges).
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch

from server.frames.frame import RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.fsr1.upscaler import frame_color

LOBES = 2


def lanczos(x: torch.Tensor, a: int = LOBES) -> torch.Tensor:
    """Lanczos-a kernel ``sinc(x) sinc(x / a)`` for |x| < a, else 0 (float64)."""
    inside = (x.abs() < a).to(x.dtype)
    return torch.sinc(x) * torch.sinc(x / a) * inside


def axis_weights(n_in: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n_out, K) clamped input indices and normalized weights along one axis."""
    scale = n_in / n_out
    stretch = max(scale, 1.0)
    support = LOBES * stretch
    centre = (torch.arange(n_out, dtype=torch.float64) + 0.5) * scale - 0.5
    first = torch.floor(centre - support) + 1
    taps = math.ceil(2 * support)  # integers inside the open interval (centre -+ support)
    pos = first.unsqueeze(1) + torch.arange(taps, dtype=torch.float64)
    weights = lanczos((pos - centre.unsqueeze(1)) / stretch)
    weights /= weights.sum(dim=1, keepdim=True)
    index = pos.clamp(0, n_in - 1).to(torch.long)
    return index, weights


class Lanczos2Upscaler(Upscaler):
    """Lanczos-2 in float32 on ``device``; any scale, up or down."""

    name: ClassVar[str] = "lanczos2"

    def __init__(
        self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
    ) -> None:
        self.device = torch.device(device)
        self.dtype = dtype
        self._key: tuple[object, ...] | None = None
        self._axes: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    def _plan(
        self, in_hw: tuple[int, int], out_hw: tuple[int, int], device: torch.device
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        key = (in_hw, out_hw, device)
        if self._axes is None or self._key != key:
            self._axes = plan_axes(in_hw, out_hw, device, self.dtype)
            self._key = key
        return self._axes

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        color = frame_color(frame, self.device)
        return self.resample(color, (display_size.height, display_size.width))

    def resample(self, image: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
        """(3, H, W) uint8 or float [0, 1] -> (3, H_out, W_out) float in [0, 1]."""
        ix, wx, iy, wy = self._plan((image.shape[1], image.shape[2]), out_hw, image.device)
        src = image.to(self.dtype)
        if image.dtype == torch.uint8:
            src.div_(255.0)
        return apply_axes(src, ix, wx, iy, wy).clamp_(0.0, 1.0)


def plan_axes(
    in_hw: tuple[int, int],
    out_hw: tuple[int, int],
    device: torch.device,
    dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The tap tables ``apply_axes`` takes."""
    ix, wx = axis_weights(in_hw[1], out_hw[1])
    iy, wy = axis_weights(in_hw[0], out_hw[0])
    return (
        ix.t().contiguous().to(device),
        wx.t().to(dtype).unsqueeze(2).contiguous().to(device),  # (K, W_out, 1)
        iy.t().contiguous().to(device),
        wy.t().to(dtype).unsqueeze(2).contiguous().to(device),  # (K, H_out, 1)
    )


def apply_axes(
    planes: torch.Tensor, ix: torch.Tensor, wx: torch.Tensor, iy: torch.Tensor, wy: torch.Tensor
) -> torch.Tensor:
    """(C, H, W) float planes through the separable tables: (C, H_out, W_out), not clamped
    (the negative lobes overshoot at edges; the caller decides what range is valid)."""
    c, h, _ = planes.shape
    wo, ho = ix.shape[1], iy.shape[1]
    # Columns on the transposed image, so that every tap gathers whole rows.
    src = planes.transpose(1, 2).contiguous()
    across = torch.zeros((c, wo, h), dtype=planes.dtype, device=planes.device)
    for k in range(ix.shape[0]):
        across.addcmul_(src.index_select(1, ix[k]), wx[k])
    rows = across.transpose(1, 2).contiguous()  # (C, H, W_out)
    out = torch.zeros((c, ho, wo), dtype=planes.dtype, device=planes.device)
    for k in range(iy.shape[0]):
        out.addcmul_(rows.index_select(1, iy[k]), wy[k])
    return out
