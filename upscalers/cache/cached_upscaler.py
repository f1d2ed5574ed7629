"""CachedUpscaler: a neural upscaler whose deep branches are reused between refreshes.

Per frame: build the network input, ask the policy "refresh now?", run the
network in refresh or reuse mode, and hand the output back to the upscaler as
its history. A policy that ``decides_late`` (the budget policy) is asked a
second time after the reuse pass, with the cache points' input delta; if it
then refreshes, the reuse output it discards is an audit of the cache's error.

What the wrapped upscaler provides (``NeuralUpscalerLike``) is the contract of
upscalers/neural: ``model``, ``features``, ``run``, ``remember``,
``reset``, and optionally ``to_display`` (network image -> display size).

Safety rules it adds to any policy's answer:

- non-finite input runs the whole network with the cache untouched by it
  (PASSTHROUGH), then empties the cache and forgets the reference input, so
  nothing non-finite is ever kept and the next frame refreshes;
- a change of render size, display size, dtype or device empties the cache
  (what was kept belongs to another resolution);
- a reuse the cache cannot serve falls back to a refresh (``LayerCache``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from server.frames.frame import FrameFlags, RenderFrame, Size
from upscalers.cache.layer_cache import CacheMode, LayerCache
from upscalers.cache.policies import CachePolicy, make_policy
from upscalers.cache.policies.budget import psnr_db
from upscalers.cache.signals import FrameSignals


class NeuralUpscalerLike(Protocol):
    @property
    def model(self) -> nn.Module: ...

    def features(self, frame: RenderFrame, display_size: Size) -> torch.Tensor: ...

    def run(self, features: torch.Tensor) -> torch.Tensor: ...

    def remember(self, output: torch.Tensor) -> None: ...

    def reset(self) -> None: ...


@dataclass
class CacheStats:
    frames: int = 0
    refreshes: int = 0  # frames that ran the whole network (chosen or forced)
    forced: int = 0  # of which the policy had no say: first, cut, bad input, cold cache
    cached: int = 0  # frames that reused the cache (ReFrame's "skipped frames")
    audits: int = 0  # refreshes that also ran the cached path to measure its error
    nonfinite: int = 0  # frames with NaN/Inf input
    invalidations: int = 0  # resolution/dtype/device changes and resets
    cache_bytes: int = 0  # what the layer cache holds now
    peak_cache_bytes: int = 0
    reference_bytes: int = 0  # the colour kept for the frame delta

    @property
    def cached_share(self) -> float:
        return 0.0 if self.frames == 0 else self.cached / self.frames

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "cached_share": self.cached_share}


class CachedUpscaler:
    """Wraps a neural upscaler with a ``LayerCache`` at ``config`` and a policy."""

    def __init__(
        self,
        upscaler: NeuralUpscalerLike,
        policy: CachePolicy | str = "delta_l",
        config: str | None = None,
    ) -> None:
        self.upscaler = upscaler
        self.policy = make_policy(policy) if isinstance(policy, str) else policy
        self.cache = LayerCache(upscaler.model, config)
        self.cache.probe_inputs = self.policy.decides_late
        self.stats = CacheStats()
        self._reference: npt.NDArray[np.uint8] | None = None
        self._since_refresh = 0
        self._geometry: tuple[Any, ...] | None = None
        # What the last frame did: "refresh", "cached", "forced" or "nonfinite".
        self.last_action = ""

    @property
    def config(self) -> str:
        return self.cache.config

    def set_policy(self, policy: CachePolicy) -> None:
        """Decide with ``policy`` from the next frame on. The cache is emptied, so that
        frame refreshes (forced): the new policy starts from a full pass, with its
        input probes, as on a first frame. History and statistics are kept."""
        self.policy = policy
        self.cache.probe_inputs = policy.decides_late
        self._invalidate()

    def reset(self) -> None:
        """Forget history and cache (scene cut, size change); the policy keeps what it
        learned, and restarts its schedule on the forced refresh that follows."""
        self.upscaler.reset()
        self._invalidate()

    def close(self) -> None:
        """Give the network its original branches back."""
        self.cache.restore()

    def _invalidate(self) -> None:
        self.cache.invalidate()
        self._reference = None
        self.stats.invalidations += 1

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        """The display-size (3, H, W) float frame, cached or not as the policy says."""
        x = self.upscaler.features(frame, display_size)
        geometry = (frame.size, display_size, tuple(x.shape), x.dtype, x.device)
        if geometry != self._geometry:
            if self._geometry is not None:
                self._invalidate()
            self._geometry = geometry
        signals = FrameSignals(
            inputs=x,
            image=frame.color,
            reference=self._reference,
            since_refresh=self._since_refresh,
            scene_cut=bool(frame.meta.flags & FrameFlags.RESET),
            cache_ready=self.cache.warm,
            motion=frame.motion,
        )
        refresh = self.policy.decide(signals)
        if not signals.finite:
            y = self._run_nonfinite(x)
        elif refresh:
            y = self._refresh(x, frame, forced=signals.must_refresh)
        elif self.policy.decides_late:
            y = self._reuse_or_refresh(x, frame)
        else:
            y = self._reuse(x, frame)
        self.upscaler.remember(y)
        self._count_frame()
        to_display = getattr(self.upscaler, "to_display", None)
        if callable(to_display):  # NeuralUpscaler: the network's 2x image -> display size
            out: torch.Tensor = to_display(y, display_size)
            return out
        return y[0]

    def _run_nonfinite(self, x: torch.Tensor) -> torch.Tensor:
        with self.cache.using(CacheMode.PASSTHROUGH):
            y = self.upscaler.run(x)
        self._invalidate()
        self._since_refresh = 0
        self.stats.nonfinite += 1
        self.stats.refreshes += 1
        self.stats.forced += 1
        self.last_action = "nonfinite"
        return y

    def _refresh(self, x: torch.Tensor, frame: RenderFrame, forced: bool) -> torch.Tensor:
        with self.cache.using(CacheMode.REFRESH):
            y = self.upscaler.run(x)
        self._count_refresh(frame, forced)
        return y

    def _count_refresh(self, frame: RenderFrame, forced: bool) -> None:
        self._kept_reference(frame)
        self.stats.refreshes += 1
        self.stats.forced += int(forced)
        self.last_action = "forced" if forced else "refresh"

    def _reuse(self, x: torch.Tensor, frame: RenderFrame) -> torch.Tensor:
        with self.cache.using(CacheMode.REUSE):
            y = self.upscaler.run(x)
        self._count_reuse(frame)
        return y

    def _count_reuse(self, frame: RenderFrame) -> None:
        if self.cache.last_forward_reused:
            self._since_refresh += 1
            self.stats.cached += 1
            self.last_action = "cached"
        else:  # the cache fell back to running the branches: that was a refresh
            self._count_refresh(frame, forced=True)

    def _reuse_or_refresh(self, x: torch.Tensor, frame: RenderFrame) -> torch.Tensor:
        """A late-deciding policy: run the cached path, then let the policy look at the
        cache points' input delta; on a refresh, the discarded cached output is the
        audit (its error against the full output, at that delta)."""
        with self.cache.using(CacheMode.REUSE):
            stale = self.upscaler.run(x)
        if not self.cache.last_forward_reused:
            self._count_reuse(frame)  # the cache could not serve it: already a refresh
            return stale
        delta = self.cache.input_delta()
        if not self.policy.refresh_late(delta):
            self._count_reuse(frame)
            return stale
        y = self._refresh(x, frame, forced=False)
        self.stats.audits += 1
        self.policy.observe_audit(delta, psnr_db(y, stale))
        return y

    def _kept_reference(self, frame: RenderFrame) -> None:
        # A copy: the frame's planes are views of a ring slot that will be reused.
        self._reference = frame.color.copy()
        self._since_refresh = 1

    def _count_frame(self) -> None:
        s = self.stats
        s.frames += 1
        s.cache_bytes = self.cache.nbytes
        s.peak_cache_bytes = max(s.peak_cache_bytes, s.cache_bytes)
        ref = self._reference
        s.reference_bytes = 0 if ref is None else ref.nbytes
