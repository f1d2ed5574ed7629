"""Config names -> upscaler classes. New methods register here, nowhere else."""

from __future__ import annotations

from collections.abc import Callable

from upscalers.base import Upscaler
from upscalers.fsr1 import EasuRcasUpscaler, EasuUpscaler
from upscalers.lanczos import Lanczos2Upscaler
from upscalers.resample import BicubicUpscaler, BilinearUpscaler, NearestUpscaler
from upscalers.temporal import TemporalUpscaler

_REGISTRY: dict[str, Callable[[], Upscaler]] = {
    cls.name: cls
    for cls in (
        NearestUpscaler,
        BilinearUpscaler,
        BicubicUpscaler,
        Lanczos2Upscaler,
        EasuUpscaler,
        EasuRcasUpscaler,
        TemporalUpscaler,
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


def create(name: str) -> Upscaler:
    """A new upscaler by config name; unknown names list the allowed ones."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown upscaler {name!r}; allowed: {', '.join(available())}") from None
    return factory()
