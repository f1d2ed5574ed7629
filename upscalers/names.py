"""The config names of the upscalers, frame predictors and cache policies, without them.

Config validation (``server/config_types.py``) checks names here, so the models
that the relay-side commands load (a control request, a synthetic publisher's
status) import nothing heavy: the base install has no torch or numba
(``pyproject.toml``, extra ``game``). The registries (``upscalers.registry``,
``upscalers.framegen``, ``upscalers.cache.policies``) stay the one place that maps
a name to its implementation; ``tests/test_names.py`` checks that these lists are
theirs, so a method registered there and not named here fails a test.

Standard library only: this module must import on the base install.
"""

from __future__ import annotations

import math
from collections.abc import Callable

# As upscalers.registry.available(): sorted.
UPSCALERS: tuple[str, ...] = (
    "bicubic",
    "bilinear",
    "cv_area",
    "cv_cubic",
    "cv_lanczos4",
    "easu",
    "easu_rcas",
    "lanczos2",
    "nearest",
    "temporal",
    "unet",
    "unet_cached",
    "unetpp",
)

# Methods that accumulate jittered frames (upscalers.registry.is_temporal).
TEMPORAL_UPSCALERS: frozenset[str] = frozenset({"temporal", "unet", "unet_cached", "unetpp"})

# As upscalers.framegen.available(): registration order, the order errors list them in.
PREDICTORS: tuple[str, ...] = ("repeat", "splat", "backward_warp", "mpe")

# The upsamplings a network's residual can be added to (upscalers.neural.features):
# "bilinear" is every checkpoint's from before they were recorded, and a new network's
# unless asked otherwise; "cubic" is Catmull-Rom.
NETWORK_BASES: tuple[str, ...] = ("bilinear", "cubic")
DEFAULT_NETWORK_BASE = "bilinear"

# Cache policies by plain name (upscalers.cache.policies.registry), sorted.
CACHE_POLICIES: tuple[str, ...] = (
    "budget",
    "deepcache",
    "delta_h",
    "delta_h_paper",
    "delta_l",
    "delta_l_paper",
    "every_1",
    "every_2",
    "every_5",
    "motion",
)

# Families written NAME@VALUE, each with the rule its policy's constructor enforces
# on VALUE (checked again here: a bad value must fail when the config is read, not
# when the worker builds the policy).
_FAMILY_RULES: dict[str, tuple[Callable[[float], bool], str]] = {
    "budget": (math.isfinite, "a finite PSNR in dB"),
    "delta": (lambda tau: tau >= 0.0, "tau >= 0"),
    "every": (lambda n: math.isfinite(n) and n == int(n) and n >= 1, "a whole N >= 1"),
    "motion": (lambda tau_px: tau_px > 0.0, "tau_px > 0"),
}
CACHE_POLICY_FAMILIES: tuple[str, ...] = tuple(sorted(_FAMILY_RULES))


def cache_policies() -> list[str]:
    """Every policy name as upscalers.cache.policies.available() lists it."""
    return list(CACHE_POLICIES) + [f"{family}@VALUE" for family in CACHE_POLICY_FAMILIES]


def check_upscaler(name: str) -> str:
    if name not in UPSCALERS:
        raise ValueError(f"unknown upscaler {name!r}; allowed: {', '.join(UPSCALERS)}")
    return name


def check_network_base(name: str) -> str:
    if name not in NETWORK_BASES:
        raise ValueError(f"unknown base {name!r}; allowed: {', '.join(NETWORK_BASES)}")
    return name


def check_predictor(name: str) -> str:
    if name not in PREDICTORS:
        raise ValueError(f"unknown frame predictor {name!r}; allowed: {', '.join(PREDICTORS)}")
    return name


def check_cache_policy(spec: str) -> str:
    """``spec`` without surrounding blanks if make_policy would accept it; else the
    ValueError it would raise (unknown names list the allowed ones)."""
    spec = spec.strip()
    if spec in CACHE_POLICIES:
        return spec
    family, sep, value = spec.partition("@")
    if sep and family in _FAMILY_RULES:
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"policy {spec!r}: {value!r} is not a number") from None
        holds, rule = _FAMILY_RULES[family]
        if not holds(number):
            raise ValueError(f"policy {spec!r}: {family} needs {rule}, got {value}")
        return spec
    raise ValueError(f"unknown cache policy {spec!r}; allowed: {', '.join(cache_policies())}")
