"""Method labels of the upscaler evaluation: a registry name plus options.

``easu_rcas@1.5`` is easu_rcas with RCAS at 1.5 stops (the sharpness sweep);
``easu_rcas+compiled`` is easu_rcas with its torch.compile path and
``easu_rcas+torch`` with its eager torch path (where the default on the CPU is a
numba kernel, or for bilinear OpenCV's resize), so one run times the
implementations side by side.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from upscalers import registry


@dataclass(frozen=True)
class MethodSpec:
    label: str  # as written in the report
    name: str  # registry name
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def temporal(self) -> bool:
        return registry.is_temporal(self.name)


COMPILED = "+compiled"
EAGER_TORCH = "+torch"
# Label suffix -> (constructor option, value, what a method without the option lacks).
_VARIANTS = {
    COMPILED: ("compile", True, "compiled path"),
    EAGER_TORCH: ("backend", "torch", "numba kernel or library resampler to swap for eager torch"),
}


def parse_method(label: str) -> MethodSpec:
    """``NAME[@SHARPNESS][+compiled|+torch]`` (RCAS stops; torch.compile path; eager
    torch instead of the numba CPU kernel or OpenCV); unknown names list the allowed ones."""
    base, variant = label, None
    for suffix in _VARIANTS:
        if label.endswith(suffix):
            base, variant = label.removesuffix(suffix), suffix
    name, at, sharp = base.partition("@")
    if name not in registry.available():
        raise ValueError(f"unknown method {name!r}; allowed: {', '.join(registry.available())}")
    options: dict[str, Any] = {}
    if at:
        try:
            options["sharpness"] = float(sharp)
        except ValueError:
            raise ValueError(f"{label!r}: sharpness after '@' must be a number") from None
    if variant is not None:
        option, value, lacking = _VARIANTS[variant]
        if not registry.takes_option(name, option):
            raise ValueError(f"{label!r}: {name} has no {lacking}")
        options[option] = value
    # Build once so a bad option fails here, before any rendering (compiling is lazy).
    registry.create(name, **options)
    return MethodSpec(label, name, options)


def sharpness_variants(values: list[float]) -> list[str]:
    return [f"easu_rcas@{v:g}" for v in values]


def compiled_variants(labels: list[str]) -> list[str]:
    """``label+compiled`` for every method in ``labels`` that has a compiled path."""
    return _variants(labels, COMPILED)


def eager_torch_variants(labels: list[str]) -> list[str]:
    """``label+torch`` for every method in ``labels`` whose CPU default is not torch."""
    return _variants(labels, EAGER_TORCH)


def _variants(labels: list[str], suffix: str) -> list[str]:
    option = _VARIANTS[suffix][0]
    return [
        m + suffix
        for m in labels
        if not any(m.endswith(s) for s in _VARIANTS)
        and registry.takes_option(m.partition("@")[0], option)
    ]
