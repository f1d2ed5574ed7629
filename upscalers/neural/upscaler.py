"""NeuralUpscaler: the trained U-Net / U-Net++ behind the one upscaler interface.

``upscale`` = ``features`` (frame contract + own warped previous output ->
network input) + ``run`` (network -> display image) + ``remember`` (keep the
image as the next frame's history). The three are public so the layer cache
(``upscalers/cache``) can ask its policy "refresh now?" between them.

The networks are trained for 2x. Any other display size is served by the 2x
output resampled to it (bilinear, antialiased when shrinking) rather than
refused: the evaluation's default scales and a run-time scale switch in the
worker must not crash the worker. History stays at the network's 2x size.

It is a temporal method (the game jitters for it): jitter is one of its inputs,
and its previous output, warped by the motion vectors, accumulates detail.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import torch
import torch.nn.functional as F

from server.frames.frame import RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.neural.features import FrameTensors, History, build_features
from upscalers.neural.network import WEIGHTS_DIR, load_checkpoint, predict, with_memory_format
from upscalers.temporal import ops


def frame_tensors(frame: RenderFrame, device: torch.device, dtype: torch.dtype) -> FrameTensors:
    color = ops.as_tensor(frame.color, device).permute(2, 0, 1).unsqueeze(0)
    depth = ops.as_tensor(frame.depth, device).unsqueeze(0).unsqueeze(0)
    motion = ops.as_tensor(frame.motion, device).permute(2, 0, 1).unsqueeze(0)
    nf = ops.near_far(frame)
    return FrameTensors(
        color=color.to(dtype).div_(255.0),
        depth=depth.float(),
        motion=motion.float(),
        jitter=torch.tensor([ops.jitter(frame)], dtype=torch.float32, device=device),
        near_far=None if nf is None else torch.tensor([nf], dtype=torch.float32, device=device),
    )


class NeuralUpscaler(Upscaler):
    temporal: ClassVar[bool] = True
    network: ClassVar[str]

    def __init__(
        self,
        *,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        weights: str | Path | None = None,
    ) -> None:
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        self.dtype = dtype
        path = Path(weights) if weights is not None else WEIGHTS_DIR / f"{self.network}.pt"
        name, model, self.scale, self.meta = load_checkpoint(path)
        if name != self.network:
            raise ValueError(f"{path} holds a {name!r} network, not {self.network!r}")
        self.model = model.to(self.device, dtype)
        if self.device.type == "cpu":
            # channels-last convolutions are about twice as fast on the CPU (measured).
            self.model = with_memory_format(self.model, torch.channels_last)
        self._history: History | None = None
        self._pending_depth: torch.Tensor | None = None
        self._key: tuple[int, int, int, int] | None = None

    def reset(self) -> None:
        self._history = None
        self._pending_depth = None

    def features(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        """(1, C, h, w) network input; resets history when the render or display size
        changed since the last frame."""
        h, w = frame.depth.shape[:2]
        key = (w, h, int(display_size[0]), int(display_size[1]))
        if key != self._key:
            self.reset()
            self._key = key
        tensors = frame_tensors(frame, self.device, self.dtype)
        x, self._pending_depth = build_features(tensors, self._history, self.scale)
        if self.device.type == "cpu":
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def run(self, features: torch.Tensor) -> torch.Tensor:
        """The network's image (1, 3, s h, s w), float sRGB in [0, 1], finite."""
        with torch.no_grad():
            y = predict(self.model, features, self.scale)
        return torch.nan_to_num(y, nan=0.0, posinf=1.0, neginf=0.0).contiguous()

    def remember(self, output: torch.Tensor) -> None:
        """Keep ``output`` (from ``run``) as the history the next frame warps."""
        if self._pending_depth is None:
            raise RuntimeError("remember() needs the features() of the same frame first")
        self._history = History(output.detach(), self._pending_depth)
        self._pending_depth = None

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        y = self.run(self.features(frame, display_size))
        self.remember(y)
        return self.to_display(y, display_size)

    @staticmethod
    def to_display(output: torch.Tensor, display_size: Size) -> torch.Tensor:
        """(1, 3, H', W') network image -> (3, H, W) at the display size."""
        big_w, big_h = int(display_size[0]), int(display_size[1])
        if output.shape[-2:] == (big_h, big_w):
            return output[0]
        shrink = big_h < output.shape[-2] or big_w < output.shape[-1]
        resized = F.interpolate(
            output.float(), size=(big_h, big_w), mode="bilinear", align_corners=False,
            antialias=shrink,
        )  # fmt: skip
        return resized[0].clamp_(0.0, 1.0).to(output.dtype)


class UNetUpscaler(NeuralUpscaler):
    """U-Net with skip concatenations (``upscalers/neural/unet.py``)."""

    name: ClassVar[str] = "unet"
    network: ClassVar[str] = "unet"


class UNetPlusPlusUpscaler(NeuralUpscaler):
    """U-Net++ with nested skip paths (``upscalers/neural/unetpp.py``)."""

    name: ClassVar[str] = "unetpp"
    network: ClassVar[str] = "unetpp"


UPSCALERS: dict[str, type[NeuralUpscaler]] = {
    cls.network: cls for cls in (UNetUpscaler, UNetPlusPlusUpscaler)
}


def load(
    name: str, device: str | torch.device | None = None, dtype: torch.dtype = torch.float32
) -> NeuralUpscaler:
    """The shipped network ``name`` ("unet" or "unetpp") ready to upscale."""
    try:
        cls = UPSCALERS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r}; allowed: {', '.join(UPSCALERS)}") from None
    return cls(device=device, dtype=dtype)
