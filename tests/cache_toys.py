"""Small cacheable networks and a NeuralUpscaler-like wrapper for the cache tests.

They follow the contract of upscalers/cache/points.py the way the real networks
do, with random weights: a recursive U-Net (``ToyUNet``) and a network with
parallel branches of different depths fed to one last block (``ToyNested``,
U-Net++-like: several cached inputs to one concatenation, keyword arguments).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size

IN_CHANNELS = 9  # colour 3, depth 1, motion 2, warped previous output 3
TOY_SIZE = Size(32, 24)


def _block(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU())


class Level(nn.Module):
    """enc -> (inner) -> dec(cat(enc_out, inner(enc_out))); the deepest has no inner."""

    def __init__(self, channels: int, depth: int) -> None:
        super().__init__()
        self.enc = _block(channels, channels)
        self.inner = Inner(channels, depth - 1) if depth > 1 else None
        self.dec = _block(2 * channels if self.inner is not None else channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = self.enc(x)
        if self.inner is None:
            return self.dec(e)  # type: ignore[no-any-return]
        return self.dec(torch.cat([e, self.inner(e)], dim=1))  # type: ignore[no-any-return]


class Inner(nn.Module):
    """Downsample -> deeper level -> upsample: one submodule, so it can be skipped whole."""

    def __init__(self, channels: int, depth: int) -> None:
        super().__init__()
        self.down = nn.Conv2d(channels, channels, 3, stride=2, padding=1)
        self.level = Level(channels, depth)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.level(F.relu(self.down(x)))
        return F.interpolate(y, size=x.shape[-2:], mode="nearest")


class ToyUNet(nn.Module):
    cache_configs: ClassVar[dict[str, tuple[str, ...]]] = {
        "1": ("body.inner",),
        "2": ("body.inner.level.inner",),
        "3": ("body.inner.level.inner.level.inner",),
    }
    default_cache_config: ClassVar[str] = "1"

    def __init__(self, channels: int = 8, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.head = _block(IN_CHANNELS, channels)
        self.body = Level(channels, depth=4)
        self.tail = nn.Conv2d(channels, 3, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.tail(self.body(self.head(x)))
        return torch.sigmoid(F.interpolate(y, scale_factor=2.0, mode="bilinear"))


class DeepBranch(nn.Module):
    def __init__(self, channels: int, downs: int) -> None:
        super().__init__()
        self.downs = nn.ModuleList(
            nn.Conv2d(channels, channels, 3, stride=2, padding=1) for _ in range(downs)
        )
        self.mix = _block(channels, channels)

    def forward(self, x: torch.Tensor, *, skip: torch.Tensor) -> torch.Tensor:
        y = x
        for down in self.downs:
            y = F.relu(down(y))
        y = F.interpolate(self.mix(y), size=x.shape[-2:], mode="nearest")
        return y + skip


class ToyNested(nn.Module):
    cache_configs: ClassVar[dict[str, tuple[str, ...]]] = {
        "A": ("mid", "deep"),
        "B": ("deep",),
    }
    default_cache_config: ClassVar[str] = "B"

    def __init__(self, channels: int = 6, seed: int = 1) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.stem = _block(IN_CHANNELS, channels)
        self.mid = DeepBranch(channels, downs=1)
        self.deep = DeepBranch(channels, downs=2)
        self.last = nn.Conv2d(3 * channels, 3, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.stem(x)
        y = self.last(torch.cat([s, self.mid(s, skip=s), self.deep(s, skip=s)], dim=1))
        return torch.sigmoid(F.interpolate(y, scale_factor=2.0, mode="nearest"))


class ToyNeuralUpscaler:
    """The NeuralUpscaler contract (features, run, remember, reset, model) around a toy."""

    def __init__(
        self, model: nn.Module, dtype: torch.dtype = torch.float32, *, feedback: bool = True
    ) -> None:
        self.model = model
        self.dtype = dtype
        # feedback=False: the previous output is not fed back, so an uncached twin
        # sees exactly the same inputs whatever the cache did before.
        self.feedback = feedback
        self.history: torch.Tensor | None = None

    def features(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        device = next(self.model.parameters()).device
        color = torch.from_numpy(frame.color.astype(np.float32) / 255.0).permute(2, 0, 1)
        depth = torch.from_numpy(np.array(frame.depth, dtype=np.float32))[None]
        motion = torch.from_numpy(np.array(frame.motion, dtype=np.float32)).permute(2, 0, 1)
        h, w = frame.depth.shape
        shape = (display_size.height, display_size.width)
        if not self.feedback or self.history is None or self.history.shape[-2:] != shape:
            prev = torch.zeros(3, h, w)
        else:
            prev = F.interpolate(self.history.float(), size=(h, w), mode="area")[0].cpu()
        x = torch.cat([color, depth, motion / 8.0, prev])[None]
        return x.to(device=device, dtype=self.dtype)

    def run(self, features: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.model(features)  # type: ignore[no-any-return]

    def remember(self, output: torch.Tensor) -> None:
        self.history = output.detach()

    def reset(self) -> None:
        self.history = None

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        y = self.run(self.features(frame, display_size))
        self.remember(y)
        return y[0]


def make_frame(
    index: int,
    size: Size = TOY_SIZE,
    *,
    shift: int = 1,
    flags: FrameFlags = FrameFlags.NONE,
    seed: int = 0,
) -> RenderFrame:
    """A textured frame that pans ``shift`` pixels a frame (motion says so)."""
    rng = np.random.default_rng(seed)
    w, h = size
    base = rng.integers(0, 256, size=(h, w + 64, 3), dtype=np.uint8)
    off = (index * shift) % 64
    color = np.ascontiguousarray(base[:, off : off + w])
    depth = np.full((h, w), 0.5, dtype=np.float32)
    motion = np.zeros((h, w, 2), dtype=np.float32)
    motion[..., 0] = float(shift)
    meta = FrameMeta(frame_id=index, camera=Camera.identity(), flags=flags)
    return RenderFrame(color, depth, motion, np.zeros((h, w), dtype=np.uint8), meta)


def display_of(size: Size) -> Size:
    return Size(size.width * 2, size.height * 2)
