"""Config names -> upscaler classes. New methods register here, nowhere else."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from upscalers.base import Upscaler
from upscalers.cache.unet_cached import CachedUNetUpscaler
from upscalers.fsr1.upscaler import EasuRcasUpscaler, EasuUpscaler
from upscalers.neural.upscaler import UNetPlusPlusUpscaler, UNetUpscaler
from upscalers.spatial.cv_resample import CvAreaUpscaler, CvCubicUpscaler, CvLanczos4Upscaler
from upscalers.spatial.lanczos import Lanczos2Upscaler
from upscalers.spatial.resample import BicubicUpscaler, BilinearUpscaler, NearestUpscaler
from upscalers.temporal.upscaler import TemporalUpscaler

_REGISTRY: dict[str, Callable[..., Upscaler]] = {
    cls.name: cls
    for cls in (
        NearestUpscaler,
        BilinearUpscaler,
        BicubicUpscaler,
        Lanczos2Upscaler,
        CvCubicUpscaler,
        CvLanczos4Upscaler,
        CvAreaUpscaler,
        EasuUpscaler,
        EasuRcasUpscaler,
        TemporalUpscaler,
        UNetUpscaler,
        UNetPlusPlusUpscaler,
        CachedUNetUpscaler,
    )
}


def available() -> list[str]:
    return sorted(_REGISTRY)


def is_temporal(name: str) -> bool:
    """Whether the method accumulates jittered frames (the game must jitter for it).

    Spatial methods get unjittered frames: jitter without accumulation is only
    shimmer, and bits the encoder spends on a still scene."""
    factory = _REGISTRY.get(name)
    return isinstance(factory, type) and issubclass(factory, Upscaler) and factory.temporal


def create(name: str, **options: Any) -> Upscaler:
    """A new upscaler by config name; unknown names list the allowed ones.

    ``options`` go to the method's constructor (e.g. ``sharpness`` of easu_rcas);
    an option the method does not take is refused with the ones it does."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown upscaler {name!r}; allowed: {', '.join(available())}") from None
    if options:
        allowed = _keyword_options(factory)
        unknown = sorted(set(options) - allowed)
        if unknown:
            raise ValueError(
                f"upscaler {name!r} takes no option {', '.join(unknown)}; "
                f"allowed: {', '.join(sorted(allowed)) or 'none'}"
            )
    return factory(**options)


def takes_option(name: str, option: str) -> bool:
    """Whether method ``name`` has constructor option ``option`` (e.g. ``compile``)."""
    factory = _REGISTRY.get(name)
    return factory is not None and option in _keyword_options(factory)


def cache_policy_at_start(name: str, chosen: str | None) -> str | None:
    """The cache policy method ``name`` starts with: ``chosen``, else its own default;
    None for a method without a layer cache."""
    factory = _REGISTRY.get(name)
    if factory is None or not takes_option(name, "policy"):
        return None
    if chosen is not None:
        return chosen
    default = inspect.signature(factory).parameters["policy"].default
    return default if isinstance(default, str) else None


def _keyword_options(factory: Callable[..., Upscaler]) -> set[str]:
    params = inspect.signature(factory).parameters.values()
    return {p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
