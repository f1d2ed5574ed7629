"""ReFrame's frame-delta policy: refresh when the input has changed enough since the cache."""

from __future__ import annotations

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.signals import FrameSignals

# The paper's Table 7: SMAPE thresholds of high (H) and low (L) sensitivity.
DELTA_H_TAU = 0.20
DELTA_L_TAU = 0.25


class DeltaPolicy(CachePolicy):
    """Refresh when SMAPE(input, input at the last refresh) exceeds ``tau``."""

    def __init__(self, tau: float, name: str | None = None) -> None:
        if not tau >= 0.0:
            raise ValueError(f"delta policy needs tau >= 0, got {tau}")
        self.tau = tau
        self.name = name or f"delta@{tau:g}"

    def _refresh_now(self, signals: FrameSignals) -> bool:
        return signals.smape > self.tau

    def describe(self) -> str:
        return f"{self.name} (SMAPE > {self.tau:g})"
