"""AMD FidelityFX Super Resolution 1 (spatial): EASU, and EASU followed by RCAS.

The math lives in ``fsr1_easu`` and ``fsr1_rcas``; this module adapts it to the
upscaler interface. Both run on the device given at construction (CPU by default;
a CUDA device moves the colour plane there) in float32, or in float16 on CUDA
when asked.
"""

from __future__ import annotations

from typing import ClassVar

import torch

from server.frame import RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.fsr1_easu import Easu
from upscalers.fsr1_rcas import DEFAULT_SHARPNESS, Rcas
from upscalers.resample import color_as_nchw


def frame_color(frame: RenderFrame, device: torch.device) -> torch.Tensor:
    """The (3, H, W) uint8 colour plane of a frame on ``device`` (a view on the CPU)."""
    color = color_as_nchw(frame.color)[0]
    return color if device.type == "cpu" else color.to(device, non_blocking=False)


class _Fsr1Base(Upscaler):
    def __init__(
        self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
    ) -> None:
        self.device = torch.device(device)
        if dtype not in (torch.float32, torch.float16, torch.bfloat16):
            raise ValueError(f"dtype must be a float dtype, got {dtype}")
        self.dtype = dtype
        self._easu = Easu(dtype=dtype)


class EasuUpscaler(_Fsr1Base):
    """FSR 1 EASU alone: edge-adaptive Lanczos-like upscale, de-ringed, no sharpening."""

    name: ClassVar[str] = "easu"

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        color = frame_color(frame, self.device)
        return self._easu(color, (display_size.height, display_size.width))


class EasuRcasUpscaler(_Fsr1Base):
    """FSR 1 as shipped: EASU, then RCAS sharpening.

    ``sharpness`` is in stops below the strongest (FSR's convention: 0 is the
    strongest, each stop halves the effect); ``denoise`` enables RCAS's optional
    noise removal.
    """

    name: ClassVar[str] = "easu_rcas"

    def __init__(
        self,
        sharpness: float = DEFAULT_SHARPNESS,
        denoise: bool = False,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__(device, dtype)
        self._rcas = Rcas(sharpness=sharpness, denoise=denoise)
        self._padded: torch.Tensor | None = None

    @property
    def sharpness(self) -> float:
        return self._rcas.sharpness

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        color = frame_color(frame, self.device)
        h, w = display_size.height, display_size.width
        shape = (3, h + 2, w + 2)
        if (
            self._padded is None
            or self._padded.shape != shape
            or self._padded.device != color.device
        ):
            self._padded = torch.empty(shape, dtype=self.dtype, device=color.device)
        # EASU writes straight into the interior of RCAS's padded input.
        self._easu(color, (h, w), out=self._padded[:, 1:-1, 1:-1])
        return self._rcas(self._padded)
