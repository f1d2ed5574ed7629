"""The scene's motion class from what every frame already carries: its camera and flags.

Ring U frames keep the game's unjittered view matrix and the previous frame's, so
the camera's rotation and travel per frame cost a 3x3 product to read, and a scene
cut is the RESET flag. Which class a window of frames falls in picks the scenes of
the speed-against-error table the controller weighs (a temporal method's lead is
largest on a still camera and smallest across cuts):

- ``still``: the camera turned less than ``STILL_DEG`` and travelled less than
  ``STILL_TRAVEL`` per frame on average;
- ``fast``: it turned more than ``FAST_DEG`` a frame (a fast yaw smears history);
- ``cuts``: more than ``CUTS_PER_S`` scene cuts a second;
- ``slow`` otherwise; ``unknown`` for a source without a camera (a captured
  application) or before any frame: every scene weighs the same.

The thresholds sit between the evaluation's scenes: ``static`` does not move,
``slow_pan`` turns 0.3 degrees a frame at 60 fps, ``fast_yaw`` 3.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from server.frames.frame import FrameFlags, FrameMeta

SceneClass = Literal["still", "slow", "fast", "cuts", "unknown"]

STILL_DEG = 0.02
STILL_TRAVEL = 1e-3  # world units per frame
FAST_DEG = 1.5
CUTS_PER_S = 0.5
WINDOW_S = 4.0

# The evaluation's scenes that stand for each class (figures.py's table).
SCENES_OF_CLASS: dict[SceneClass, tuple[str, ...]] = {
    "still": ("static",),
    "slow": ("slow_pan", "dolly", "default", "thin_detail"),
    "fast": ("fast_yaw", "moving_objects"),
    "cuts": ("scene_cut",),
    "unknown": (),  # all of them
}


@dataclass(frozen=True)
class CameraStep:
    degrees: float  # rotation between the frame's view and the previous one
    travel: float  # camera translation, world units


def camera_step(meta: FrameMeta) -> CameraStep | None:
    """The camera's motion into this frame; None when the frame has no usable camera
    (a colour-only source, or matrices that are not finite)."""
    if meta.flags & FrameFlags.COLOR_ONLY:
        return None
    view = np.asarray(meta.camera.view, dtype=np.float64)
    prev = np.asarray(meta.camera.prev_view, dtype=np.float64)
    if view.shape != (4, 4) or prev.shape != (4, 4):
        return None
    if not (np.isfinite(view).all() and np.isfinite(prev).all()):
        return None
    rot = view[:3, :3] @ prev[:3, :3].T
    cos = (float(np.trace(rot)) - 1.0) / 2.0
    degrees = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    # Camera centres: -R^T t of each world->view matrix.
    centre = -view[:3, :3].T @ view[:3, 3]
    prev_centre = -prev[:3, :3].T @ prev[:3, 3]
    travel = float(np.linalg.norm(centre - prev_centre))
    if not (math.isfinite(degrees) and math.isfinite(travel)):
        return None
    return CameraStep(degrees, travel)


class SceneTracker:
    """Keeps the last ``window_s`` of frames' camera steps and cuts; sans-IO (``now``
    is given)."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        self._steps: deque[tuple[float, CameraStep | None, bool]] = deque()

    def frame(self, meta: FrameMeta, now: float) -> None:
        cut = bool(meta.flags & FrameFlags.RESET)
        self._steps.append((now, None if cut else camera_step(meta), cut))
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._steps and self._steps[0][0] < now - self.window_s:
            self._steps.popleft()

    def scene(self, now: float) -> SceneClass:
        self._trim(now)
        steps = [s for _, s, _ in self._steps if s is not None]
        if not steps:
            return "unknown"
        cuts = sum(1 for _, _, cut in self._steps if cut)
        span = max(1e-3, min(self.window_s, now - self._steps[0][0]))
        if cuts / span > CUTS_PER_S and len(self._steps) >= 2:
            return "cuts"
        degrees = sum(s.degrees for s in steps) / len(steps)
        travel = sum(s.travel for s in steps) / len(steps)
        if degrees >= FAST_DEG:
            return "fast"
        if degrees < STILL_DEG and travel < STILL_TRAVEL:
            return "still"
        return "slow"
