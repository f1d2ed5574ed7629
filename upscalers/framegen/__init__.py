"""Frame generation: predict the frames between rendered ones from the last rendered frame.

One interface (``FramePredictor``: ``observe`` a rendered frame, ``predict``
the view from a new camera, ``reset``) and a registry of methods:

- ``repeat``: the cached frame again.
- ``splat``: per-pixel forward reprojection with a z-buffer.
- ``backward_warp``: warp by the cached motion vectors.
- ``mpe``: Mesh Projection Estimation (Arena Breakout, GDC), per-vertex
  reprojection of a screen-space mesh with tensile and shear correction.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from upscalers.framegen.backward_warp import BackwardWarpPredictor
from upscalers.framegen.base import CachedFrame, FramePredictor, Prediction
from upscalers.framegen.mpe import MeshProjectionPredictor
from upscalers.framegen.mpe_options import DEFAULT_TILE, MpeOptions
from upscalers.framegen.repeat import RepeatPredictor
from upscalers.framegen.splat import SplatPredictor

PREDICTORS: dict[str, type[FramePredictor]] = {
    cls.name: cls
    for cls in (RepeatPredictor, SplatPredictor, BackwardWarpPredictor, MeshProjectionPredictor)
}


def available() -> list[str]:
    return list(PREDICTORS)


def create(name: str, device: str | torch.device | None = None) -> FramePredictor:
    """A predictor by config name with its defaults; unknown names list the allowed ones."""
    try:
        cls = PREDICTORS[name]
    except KeyError:
        raise ValueError(
            f"unknown frame predictor {name!r}; allowed: {', '.join(available())}"
        ) from None
    factory: Callable[..., FramePredictor] = cls
    return factory(device=device)


__all__ = [
    "DEFAULT_TILE",
    "PREDICTORS",
    "BackwardWarpPredictor",
    "CachedFrame",
    "FramePredictor",
    "MeshProjectionPredictor",
    "MpeOptions",
    "Prediction",
    "RepeatPredictor",
    "SplatPredictor",
    "available",
    "create",
]
