"""Field types shared by the pydantic models at the edges (CLI, HTTP, control).

Each checks its value once, here, with a message that names what is allowed.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator

from server.frames.frame import Size
from upscalers import framegen, registry
from upscalers.cache import policies


def _known_upscaler(name: str) -> str:
    if name not in registry.available():
        raise ValueError(f"unknown upscaler {name!r}; allowed: {', '.join(registry.available())}")
    return name


def _known_predictor(name: str) -> str:
    if name not in framegen.available():
        raise ValueError(
            f"unknown frame predictor {name!r}; allowed: {', '.join(framegen.available())}"
        )
    return name


def _known_cache_policy(name: str) -> str:
    policies.make_policy(name)  # raises ValueError listing the allowed names
    return name.strip()


def _size_text(text: str) -> str:
    Size.parse(text)  # raises ValueError naming the expected form
    return text


UpscalerName = Annotated[str, AfterValidator(_known_upscaler)]
PredictorName = Annotated[str, AfterValidator(_known_predictor)]
CachePolicyName = Annotated[str, AfterValidator(_known_cache_policy)]
SizeText = Annotated[str, AfterValidator(_size_text)]
