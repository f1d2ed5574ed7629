"""Fixed schedules: refresh every N frames, and DeepCache's non-uniform schedule.

These ignore the content (the paper's baselines); they still refresh on the
forced frames of ``CachePolicy.decide`` (first frame, cut, bad input) and count
from there.
"""

from __future__ import annotations

import math

import numpy as np

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.signals import FrameSignals


class EveryNPolicy(CachePolicy):
    """Refresh on every N-th frame (N=1: always; the cache then changes nothing)."""

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ValueError(f"every-N policy needs N >= 1, got {n}")
        self.n = n
        self.name = f"every_{n}"

    def _refresh_now(self, signals: FrameSignals) -> bool:
        return signals.since_refresh >= self.n


def _signed_power(x: float, p: float) -> float:
    """Real x**p keeping the sign (the real root for p < 1, never complex)."""
    return math.copysign(abs(x) ** p, x)


def nonuniform_schedule(total: int, refreshes: int, center: float, power: float) -> tuple[int, ...]:
    """DeepCache's non-uniform refresh steps in [0, total): dense around ``center``.

    Points spaced evenly in x = signed_root(step - center, power) from
    signed_root(-center) to signed_root(total - center) are mapped back by
    signed_power(x, power) + center, truncated toward zero like the original's
    int32 cast; the first point is 0 and the endpoint ``total`` is dropped.

    The original computes ``(-center) ** (1 / power)`` in Python, which for a
    negative base is a complex number; its real part (not the real root) then
    shifts every step. Here roots keep their sign and stay real. As in the
    original, if rounding merges steps, the power is lowered by 0.02 until
    ``refreshes`` distinct steps remain; at power 1 the steps are uniform."""
    if total < 1 or not 1 <= refreshes <= total:
        raise ValueError(f"need 1 <= refreshes <= total, got {refreshes} of {total}")
    if not 0 <= center <= total:
        raise ValueError(f"center must lie in [0, {total}], got {center}")
    if power < 1:
        raise ValueError(f"power must be >= 1, got {power}")
    p = power
    while p > 1.0:
        lo, hi = _signed_power(-center, 1 / p), _signed_power(total - center, 1 / p)
        xs = np.linspace(lo, hi, refreshes + 1)
        mapped = sorted({int(_signed_power(float(x), p)) for x in xs})
        steps = sorted({0, *(m + int(center) for m in mapped[1:-1])})
        steps = [s for s in steps if 0 <= s < total]
        if len(steps) == refreshes:
            return tuple(steps)
        p -= 0.02
    uniform = np.linspace(0, total, refreshes, endpoint=False)
    return tuple(sorted({int(s) for s in uniform}))


class NonUniformPolicy(CachePolicy):
    """DeepCache's non-uniform schedule on a stream: a period that repeats.

    DeepCache schedules ``k`` refreshes over a sampling run of ``T`` steps; a game
    stream has no end, so ``T`` is a period counted from the last forced refresh
    (start, scene cut) and the schedule repeats. The defaults follow the paper's
    Table 7 (c = 110, p = 1.4) with T = 2c (the centre mid-period) and k = T / 5
    (on average one refresh in five frames, its "Non-Linear N-5")."""

    def __init__(
        self, center: float = 110.0, power: float = 1.4, period: int = 220, mean_interval: int = 5
    ) -> None:
        refreshes = max(1, round(period / mean_interval))
        self.steps = frozenset(nonuniform_schedule(period, refreshes, center, power))
        self.period = period
        self.name = "deepcache"
        self._t = 0

    def decide(self, signals: FrameSignals) -> bool:
        refresh = super().decide(signals)
        self._t += 1
        return refresh

    def _restart(self) -> None:
        self._t = 0

    def _refresh_now(self, signals: FrameSignals) -> bool:
        return (self._t % self.period) in self.steps
