"""Motion-vector policy: refresh once the content has moved far enough since the cache."""

from __future__ import annotations

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.signals import FrameSignals

# The paper's Table 7: tau = 1 (average motion, pixels).
MOTION_TAU_PX = 1.0


class MotionPolicy(CachePolicy):
    """Refresh when the mean motion-vector length, summed over the frames since the
    last refresh, exceeds ``tau_px`` render pixels.

    The paper thresholds "average motion" without saying over what; a per-frame
    threshold would never refresh a slow pan (0.5 px a frame for ever) however
    stale the cache became, so the motion is accumulated since the refresh."""

    def __init__(self, tau_px: float = MOTION_TAU_PX) -> None:
        if not tau_px > 0.0:
            raise ValueError(f"motion policy needs tau_px > 0, got {tau_px}")
        self.tau_px = tau_px
        self.name = "motion" if tau_px == MOTION_TAU_PX else f"motion@{tau_px:g}"
        self._moved_px = 0.0

    def _refresh_now(self, signals: FrameSignals) -> bool:
        self._moved_px += signals.mean_motion_px
        if self._moved_px > self.tau_px:
            self._moved_px = 0.0
            return True
        return False

    def _restart(self) -> None:
        self._moved_px = 0.0

    def describe(self) -> str:
        return f"{self.name} (motion since refresh > {self.tau_px:g} px)"
