"""A policy that holds a quality budget by itself: it sets its own SMAPE threshold.

ReFrame leaves the sensitivity fixed (Delta_H, Delta_L) and calls a dynamic one
future work. The error a stale cache causes depends on the scene (a slow pan
forgives a larger input delta than a fast yaw over thin detail), so one fixed
threshold is either wasteful on easy scenes or over budget on hard ones.

How it learns, at almost no cost: every refresh it chooses (the SMAPE s of this
frame went over its threshold) is audited. Before the cache is refreshed the
network also runs its cheap cached path with the stale cache, and the PSNR p of
that output against the full output is the error the cache would have made on
this frame, one frame beyond the longest run it allowed. Taking the output
error as proportional to the input delta (p drops by 20 log10 of the SMAPE
ratio), the threshold that would have met the budget ``B`` with ``margin_db`` to
spare is

    tau = s * 10 ** ((p - B - margin_db) / 20).

The policy uses the smallest such estimate of its last ``window`` audits (the
hardest recent content rules), grows by at most ``max_growth`` per audit, and
starts from Delta_H's threshold. The budget is a PSNR of the cached output
against the uncached one (cheap to compute on the output tensor, unlike FLIP).
"""

from __future__ import annotations

import math
from collections import deque

import torch

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.signals import FrameSignals

# Worst-frame PSNR against the uncached output. Never refreshing for 30 frames
# stays above 45 dB on all scenes but the cut (37 dB), so a budget below that
# never binds and "never refresh" is the best policy; at 40 dB the hardest scene
# needs refreshes and the easy ones do not.
DEFAULT_BUDGET_DB = 40.0


def psnr_db(reference: torch.Tensor, test: torch.Tensor) -> float:
    """PSNR of two float images in [0, 1] (inf when identical); float32 arithmetic."""
    diff = reference.float() - test.float()
    mse = float((diff * diff).mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


class BudgetPolicy(CachePolicy):
    wants_audit = True

    def __init__(
        self,
        budget_db: float = DEFAULT_BUDGET_DB,
        *,
        start_tau: float = 0.05,
        margin_db: float = 1.0,
        window: int = 6,
        max_growth: float = 1.5,
        min_tau: float = 1e-4,
        max_tau: float = 1.0,
    ) -> None:
        if not math.isfinite(budget_db):
            raise ValueError(f"budget must be a finite PSNR in dB, got {budget_db}")
        if not 0 < min_tau <= start_tau <= max_tau:
            raise ValueError("need 0 < min_tau <= start_tau <= max_tau")
        if window < 1 or max_growth < 1.0 or margin_db < 0:
            raise ValueError("need window >= 1, max_growth >= 1 and margin_db >= 0")
        self.budget_db = budget_db
        self.start_tau = start_tau
        self.margin_db = margin_db
        self.max_growth = max_growth
        self.min_tau = min_tau
        self.max_tau = max_tau
        self.name = "budget" if budget_db == DEFAULT_BUDGET_DB else f"budget@{budget_db:g}"
        self.tau = start_tau
        self._estimates: deque[float] = deque(maxlen=window)
        self.audits = 0

    def _refresh_now(self, signals: FrameSignals) -> bool:
        return signals.smape > self.tau

    def observe_audit(self, signals: FrameSignals, stale_psnr_db: float) -> None:
        s = signals.smape
        if not math.isfinite(s) or s <= 0.0 or math.isnan(stale_psnr_db):
            return
        self.audits += 1
        headroom_db = stale_psnr_db - self.budget_db - self.margin_db
        estimate = self.max_tau if math.isinf(headroom_db) else s * 10.0 ** (headroom_db / 20.0)
        self._estimates.append(estimate)
        target = min(self._estimates)
        self.tau = min(max(target, self.min_tau), self.tau * self.max_growth, self.max_tau)

    def reset(self) -> None:
        self.tau = self.start_tau
        self._estimates.clear()
        self.audits = 0

    def describe(self) -> str:
        return f"{self.name} (worst-frame PSNR >= {self.budget_db:g} dB vs uncached, tau adapts)"
