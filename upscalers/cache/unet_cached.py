"""``unet_cached``: the shipped U-Net with ReFrame layer caching, behind the one interface."""

from __future__ import annotations

from typing import ClassVar

import torch

from server.frames.frame import RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.cache.cached_upscaler import CachedUpscaler, CacheStats
from upscalers.cache.policies import make_policy


class CachedUNetUpscaler(Upscaler):
    """The ``unet`` network whose deep branch is reused between refreshes.

    ``policy`` is a cache policy config name (``delta_l``, ``delta_h``, ``budget``,
    ``every_5``, ``delta@0.06`` ...) and ``cache_level`` one of the U-Net's cache
    configs ("1" skips the most, "3" the least); both are checked here, so a bad
    config fails when the worker starts, naming the allowed values."""

    name: ClassVar[str] = "unet_cached"
    temporal: ClassVar[bool] = True  # the U-Net accumulates jittered frames
    network: ClassVar[str] = "unet"

    def __init__(
        self,
        policy: str = "delta_l",
        cache_level: str = "1",
        device: str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        from upscalers import neural

        make_policy(policy)  # fail on a bad name before loading anything
        self.cached = CachedUpscaler(
            neural.load(self.network, device=device, dtype=dtype), policy, str(cache_level)
        )
        self._policy = policy.strip()

    @property
    def cache_policy(self) -> str | None:
        return self._policy

    def set_cache_policy(self, policy: str) -> None:
        self.cached.set_policy(make_policy(policy))
        self._policy = policy.strip()

    @property
    def stats(self) -> CacheStats:
        return self.cached.stats

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        return self.cached.upscale(frame, display_size)

    def reset(self) -> None:
        self.cached.reset()
