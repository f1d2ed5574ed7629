"""Method labels of the upscaler evaluation: a registry name plus options.

``easu_rcas@1.5`` is easu_rcas with RCAS at 1.5 stops (the sharpness sweep).
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


def parse_method(label: str) -> MethodSpec:
    """``NAME`` or ``NAME@SHARPNESS`` (RCAS stops); unknown names list the allowed ones."""
    name, at, sharp = label.partition("@")
    if name not in registry.available():
        raise ValueError(f"unknown method {name!r}; allowed: {', '.join(registry.available())}")
    options: dict[str, Any] = {}
    if at:
        try:
            options["sharpness"] = float(sharp)
        except ValueError:
            raise ValueError(f"{label!r}: sharpness after '@' must be a number") from None
    # Build once so a bad option fails here, before any rendering.
    registry.create(name, **options)
    return MethodSpec(label, name, options)


def sharpness_variants(values: list[float]) -> list[str]:
    return [f"easu_rcas@{v:g}" for v in values]
