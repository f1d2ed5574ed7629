"""Field types shared by the pydantic models at the edges (CLI, HTTP, control).

Each checks its value once, here, with a message that names what is allowed.
Names are checked against ``upscalers.names``, not the registries: the control
and status models load on the base install, which has no torch (pyproject.toml).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator

from server.frames.frame import Size
from upscalers import names


def _size_text(text: str) -> str:
    Size.parse(text)  # raises ValueError naming the expected form
    return text


UpscalerName = Annotated[str, AfterValidator(names.check_upscaler)]
PredictorName = Annotated[str, AfterValidator(names.check_predictor)]
CachePolicyName = Annotated[str, AfterValidator(names.check_cache_policy)]
SizeText = Annotated[str, AfterValidator(_size_text)]
