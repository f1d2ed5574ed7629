"""The one frame-prediction interface: observe rendered frames, predict new views.

Semantics (the same for every predictor):

- ``observe(frame)`` makes the rendered frame the cache (colour, depth,
  dynamic mask, motion, camera). Only the last observed frame is kept, so a
  RESET frame (first frame, scene cut) simply replaces everything from before
  the cut; predicting *from* it toward a later camera is allowed.
- ``predict(view, proj, flags)`` predicts the frame seen by the new camera
  from the cache. It returns None ("nothing to predict") when nothing is
  cached (first frame, after ``reset()``), when ``flags`` carries
  ``FrameFlags.RESET`` (the frame to predict lies across a scene cut from the
  cache: the game knows that, the cache cannot), or when a matrix is
  non-finite or singular. None never comes with garbage pixels.
- Dynamic objects are not predicted: pixels whose source is under the
  cached ``dynamic_mask`` are holes, to be covered by the game drawing its
  moving objects into the predicted frame (with ``Prediction.depth`` as the
  depth buffer).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import numpy.typing as npt
import torch

from server.frames.frame import FrameFlags, RenderFrame, Size
from upscalers.framegen.geometry import Reprojection

BoolArray = npt.NDArray[np.bool_]


@dataclass
class Prediction:
    """A predicted frame at the cached frame's size."""

    color: npt.NDArray[np.uint8]  # (H, W, 3) sRGB; holes already filled with a plausible guess
    holes: BoolArray  # (H, W) no reliable source: disocclusion, off-screen, dynamic, culled
    depth: npt.NDArray[np.float32]  # (H, W) predicted NDC depth, 1.0 sky or unknown
    source_frame_id: int
    filled: BoolArray  # (H, W) subset of holes whose colour is a pull-push guess (no source at all)

    @property
    def hole_share(self) -> float:
        return float(self.holes.mean()) if self.holes.size else 0.0


@dataclass
class CachedFrame:
    """The last observed frame on the predictor's device, sanitized."""

    color: torch.Tensor  # (H, W, 3) float32, 0..255
    depth: torch.Tensor  # (H, W) float32 in [0, 1], NaN -> 1 (sky)
    dynamic: torch.Tensor  # (H, W) bool
    motion: torch.Tensor  # (H, W, 2) float32, NaN -> 0
    view: npt.NDArray[np.float64]
    proj: npt.NDArray[np.float64]
    frame_id: int
    size: Size

    @staticmethod
    def from_frame(frame: RenderFrame, device: torch.device) -> CachedFrame:
        cam = frame.meta.camera
        color = torch.from_numpy(np.ascontiguousarray(frame.color)).to(device, torch.float32)
        depth = torch.from_numpy(np.ascontiguousarray(frame.depth)).to(device, torch.float32)
        depth = torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)
        motion = torch.from_numpy(np.ascontiguousarray(frame.motion)).to(device, torch.float32)
        lim = 4.0 * float(max(frame.size))
        motion = torch.nan_to_num(motion, nan=0.0, posinf=lim, neginf=-lim).clamp_(-lim, lim)
        dynamic = torch.from_numpy(np.ascontiguousarray(frame.dynamic_mask)).to(device) != 0
        return CachedFrame(
            color,
            depth,
            dynamic,
            motion,
            np.asarray(cam.view, dtype=np.float64),
            np.asarray(cam.proj, dtype=np.float64),
            frame.meta.frame_id,
            frame.size,
        )


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class FramePredictor(ABC):
    """Base of every predictor; subclasses implement ``_predict`` (and may extend ``observe``)."""

    name: ClassVar[str]

    def __init__(self, device: str | torch.device | None = None) -> None:
        self.device = torch.device(device) if device is not None else default_device()
        self._cache: CachedFrame | None = None

    @property
    def cache(self) -> CachedFrame | None:
        return self._cache

    def reset(self) -> None:
        """Forget the cache: the next ``predict`` returns None until a frame is observed."""
        self._cache = None

    def observe(self, frame: RenderFrame) -> None:
        """Cache a rendered frame (a RESET frame drops everything before the cut)."""
        self._cache = CachedFrame.from_frame(frame, self.device)

    def predict(
        self, view: npt.ArrayLike, proj: npt.ArrayLike, flags: FrameFlags = FrameFlags.NONE
    ) -> Prediction | None:
        """The frame seen from camera (view, proj), or None when there is nothing to predict."""
        cache = self._cache
        camera = None if cache is None else (cache.view, cache.proj)
        reproj = reprojection_from(camera, view, proj, flags)
        if cache is None or reproj is None:
            return None
        return self._predict(cache, reproj)

    @abstractmethod
    def _predict(self, cache: CachedFrame, reproj: Reprojection) -> Prediction: ...


def reprojection_from(
    cached_camera: tuple[npt.ArrayLike, npt.ArrayLike] | None,
    view: npt.ArrayLike,
    proj: npt.ArrayLike,
    flags: FrameFlags,
) -> Reprojection | None:
    """The cached (view, proj) -> (view, proj) reprojection, or None when there is nothing
    to predict: nothing cached, a scene cut between (RESET), a non-finite or singular matrix."""
    if cached_camera is None or flags & FrameFlags.RESET:
        return None
    return Reprojection.between(*cached_camera, view, proj)


def to_prediction(
    color: torch.Tensor,
    holes: torch.Tensor,
    depth: torch.Tensor,
    frame_id: int,
    filled: torch.Tensor | None = None,
) -> Prediction:
    """Device tensors -> the host ``Prediction`` (colour rounded and clamped to uint8)."""
    c8 = color.add(0.5).clamp_(0.0, 255.0).to(torch.uint8)
    return Prediction(
        c8.cpu().numpy(),
        holes.cpu().numpy().astype(np.bool_, copy=False),
        torch.nan_to_num(depth.to(torch.float32), nan=1.0).cpu().numpy(),
        frame_id,
        np.zeros(holes.shape, np.bool_) if filled is None else filled.cpu().numpy(),
    )
