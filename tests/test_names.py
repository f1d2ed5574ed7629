"""upscalers.names (the torch-free list config validation checks) equals the registries."""

from __future__ import annotations

import pytest

from upscalers import framegen, names, registry
from upscalers.cache import policies


def test_upscaler_names_are_the_registry_s() -> None:
    assert list(names.UPSCALERS) == registry.available()


def test_temporal_names_are_the_registry_s() -> None:
    temporal = {n for n in registry.available() if registry.is_temporal(n)}
    assert temporal == names.TEMPORAL_UPSCALERS


def test_predictor_names_are_framegen_s() -> None:
    assert list(names.PREDICTORS) == framegen.available()


def test_network_base_names_are_the_kernels() -> None:
    from upscalers.neural.features import BASE_RADIUS

    assert tuple(BASE_RADIUS) == names.NETWORK_BASES
    assert names.DEFAULT_NETWORK_BASE in names.NETWORK_BASES


def test_cache_policy_names_are_the_policies() -> None:
    assert names.cache_policies() == policies.available()


SPECS = [
    *names.CACHE_POLICIES,
    " delta_l ",
    "reuse",
    "delta_x",
    "delta",
    "every",
    "@3",
    *(
        f"{family}@{value}"
        for family in names.CACHE_POLICY_FAMILIES
        for value in ("0", "-1", "0.08", "3", "2.5", "41", "nan", "inf", "-inf", "x", "")
    ),
]


@pytest.mark.parametrize("spec", SPECS)
def test_a_cache_policy_passes_config_exactly_when_make_policy_takes_it(spec: str) -> None:
    try:
        policies.make_policy(spec)
        made = True
    except (ValueError, OverflowError):  # int(inf) of every@inf overflows
        made = False
    try:
        checked = names.check_cache_policy(spec)
    except ValueError:
        assert not made, f"config refuses {spec!r}, which make_policy takes"
    else:
        assert made, f"config takes {spec!r}, which make_policy refuses"
        assert checked == spec.strip()


def test_an_unknown_name_lists_the_allowed_ones() -> None:
    with pytest.raises(ValueError, match="unknown upscaler 'cubic'; allowed: bicubic, "):
        names.check_upscaler("cubic")
    with pytest.raises(ValueError, match="unknown frame predictor 'x'; allowed: repeat, splat"):
        names.check_predictor("x")
    with pytest.raises(ValueError, match="unknown cache policy 'reuse'; allowed: budget, "):
        names.check_cache_policy("reuse")
