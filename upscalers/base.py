"""The one upscaler interface: frame contract in, display-size frame out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, Literal

import torch

from server.frames.frame import RenderFrame, Size

# Where a method has both, "numba" runs its compiled CPU kernels and "torch" its tensor
# code (the reference, and the CUDA path); "auto" picks the kernels wherever they run.
Backend = Literal["auto", "torch", "numba"]
BACKENDS: tuple[Backend, ...] = ("auto", "torch", "numba")


def numba_can_run(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the numba kernels serve this configuration: the CPU, in float32."""
    return device.type == "cpu" and dtype == torch.float32


class Upscaler(ABC):
    """Turns a render-size frame (ring R contract) into a display-size image.

    ``upscale`` returns a (3, H, W) tensor: uint8 when the method works on
    quantized values (the fast resamplers), float32 sRGB in nominal [0, 1]
    otherwise. ``quantize_into`` turns either into the ring U slot's bytes, so
    the in-process and the decoupled path produce the same bits.
    """

    name: ClassVar[str]
    # Temporal methods keep history; the worker calls reset() on FrameFlags.RESET
    # frames and on size changes.
    temporal: ClassVar[bool] = False

    @abstractmethod
    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor: ...

    def reset(self) -> None:  # noqa: B027 - stateless methods have nothing to reset
        """Forget any history (scene cut, resolution change)."""

    @property
    def cache_policy(self) -> str | None:
        """The layer-cache policy this method runs (upscalers/cache), None without a cache."""
        return None

    def set_cache_policy(self, policy: str) -> None:
        """Run another cache policy from the next frame on (ValueError: no cache, bad name)."""
        raise ValueError(f"upscaler {self.name!r} has no layer cache to set a policy for")
