"""Method labels of the upscaler evaluation: a registry name plus options.

``easu_rcas@1.5`` is easu_rcas with RCAS at 1.5 stops (the sharpness sweep);
``easu_rcas+compiled`` is easu_rcas with its torch.compile path, so one run times
eager and compiled side by side.
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


def parse_method(label: str) -> MethodSpec:
    """``NAME[@SHARPNESS][+compiled]`` (RCAS stops; torch.compile path); unknown names
    list the allowed ones."""
    base = label.removesuffix(COMPILED)
    name, at, sharp = base.partition("@")
    if name not in registry.available():
        raise ValueError(f"unknown method {name!r}; allowed: {', '.join(registry.available())}")
    options: dict[str, Any] = {}
    if at:
        try:
            options["sharpness"] = float(sharp)
        except ValueError:
            raise ValueError(f"{label!r}: sharpness after '@' must be a number") from None
    if base != label:
        if not registry.takes_option(name, "compile"):
            raise ValueError(f"{label!r}: {name} has no compiled path")
        options["compile"] = True
    # Build once so a bad option fails here, before any rendering (compiling is lazy).
    registry.create(name, **options)
    return MethodSpec(label, name, options)


def sharpness_variants(values: list[float]) -> list[str]:
    return [f"easu_rcas@{v:g}" for v in values]


def compiled_variants(labels: list[str]) -> list[str]:
    """``label+compiled`` for every method in ``labels`` that has a compiled path."""
    return [
        m + COMPILED
        for m in labels
        if not m.endswith(COMPILED) and registry.takes_option(m.partition("@")[0], "compile")
    ]
