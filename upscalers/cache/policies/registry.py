"""Policy config names -> policies. ``NAME@VALUE`` sets the main parameter
(``delta@0.08``, ``every@3``, ``motion@2``, ``budget@32``)."""

from __future__ import annotations

from collections.abc import Callable

from upscalers.cache.policies.base import CachePolicy
from upscalers.cache.policies.budget import BudgetPolicy
from upscalers.cache.policies.delta import (
    DELTA_H_TAU,
    DELTA_L_TAU,
    PAPER_DELTA_H_TAU,
    PAPER_DELTA_L_TAU,
    DeltaPolicy,
)
from upscalers.cache.policies.motion import MotionPolicy
from upscalers.cache.policies.schedule import EveryNPolicy, NonUniformPolicy

_NAMED: dict[str, Callable[[], CachePolicy]] = {
    "every_1": lambda: EveryNPolicy(1),
    "every_2": lambda: EveryNPolicy(2),
    "every_5": lambda: EveryNPolicy(5),
    "deepcache": NonUniformPolicy,
    "delta_h": lambda: DeltaPolicy(DELTA_H_TAU, "delta_h"),
    "delta_l": lambda: DeltaPolicy(DELTA_L_TAU, "delta_l"),
    # The paper's own thresholds, for comparison (see delta.py for why they differ).
    "delta_h_paper": lambda: DeltaPolicy(PAPER_DELTA_H_TAU, "delta_h_paper"),
    "delta_l_paper": lambda: DeltaPolicy(PAPER_DELTA_L_TAU, "delta_l_paper"),
    "motion": MotionPolicy,
    "budget": BudgetPolicy,
}

_PARAMETRIC: dict[str, Callable[[float], CachePolicy]] = {
    "delta": DeltaPolicy,
    "every": lambda n: EveryNPolicy(int(n)),
    "motion": MotionPolicy,
    "budget": BudgetPolicy,
}


def available() -> list[str]:
    return sorted(_NAMED) + [f"{k}@VALUE" for k in sorted(_PARAMETRIC)]


def make_policy(spec: str) -> CachePolicy:
    """A new policy from its config name; unknown names list the allowed ones."""
    spec = spec.strip()
    if spec in _NAMED:
        return _NAMED[spec]()
    base, sep, value = spec.partition("@")
    if sep and base in _PARAMETRIC:
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"policy {spec!r}: {value!r} is not a number") from None
        if base == "every" and number != int(number):
            raise ValueError(f"policy {spec!r}: N must be a whole number")
        return _PARAMETRIC[base](number)
    raise ValueError(f"unknown cache policy {spec!r}; allowed: {', '.join(available())}")
