"""The frame contract of ring R (G-buffers) and ring U (display frames).

Conventions, fixed here once for the renderer, the rings and every upscaler:

- World space is right-handed, +y up. View space looks down -z (OpenGL style).
- ``proj`` maps view space to clip space with NDC x, y in [-1, 1] (+y up) and
  NDC z in [0, 1] (near -> 0, far -> 1, not reversed). It is *unjittered*.
- Pixel coordinates: x to the right, y down, pixel (i, j) has its centre at
  (i + 0.5, j + 0.5). ``ndc_x = 2 x / W - 1``, ``ndc_y = 1 - 2 y / H``.
- ``jitter`` (jx, jy) is in render pixels: this frame sampled pixel (i, j) at
  (i + 0.5 + jx, j + 0.5 + jy). Halton(2, 3) minus 0.5, so each is in [-0.5, 0.5).
- ``depth`` is NDC z of the unjittered projection, 1.0 where only sky is seen.
- ``motion`` (mx, my) in render pixels: the surface seen at sample position p of
  this frame was at ``p + motion`` in the previous frame (both positions from
  unjittered projections, so a still camera over a still scene has motion 0
  whatever the jitter). Moving objects move by their own transform too.
- ``dynamic_mask`` is 1 where a moving object covers the pixel, else 0.
- ``color`` is sRGB-encoded uint8 after tonemapping.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from server.frames.timing import new_stamps

U8Array = npt.NDArray[np.uint8]
F32Array = npt.NDArray[np.float32]
I64Array = npt.NDArray[np.int64]


class Size(NamedTuple):
    """An image size in pixels, width first as in "640x360"."""

    width: int
    height: int

    def __str__(self) -> str:
        return f"{self.width}x{self.height}"

    @classmethod
    def parse(cls, text: str) -> Size:
        """Parse "WIDTHxHEIGHT"; raises ValueError with the expected form."""
        try:
            w, h = (int(p) for p in text.lower().split("x"))
        except ValueError:
            raise ValueError(f"size must look like 640x360, got {text!r}") from None
        if w <= 0 or h <= 0:
            raise ValueError(f"size must be positive, got {text!r}")
        return cls(w, h)

    def scaled(self, factor: float) -> Size:
        """This size times ``factor``, rounded to whole pixels (at least 1)."""
        return Size(max(1, round(self.width * factor)), max(1, round(self.height * factor)))


class FrameFlags(IntFlag):
    NONE = 0
    # History is invalid (first frame, scene cut, teleport): temporal methods must
    # restart. Engines pass the same bit to FSR 2 / DLSS as "reset".
    RESET = 1
    # The frame was predicted (frame generation), not rendered.
    PREDICTED = 2
    # Only the colour plane is meaningful: the source (a captured X11 display, a video)
    # has no depth, motion or jitter, and the slot's other planes are undefined. Only
    # spatial upscalers may run on such a frame and no frame can be predicted from it.
    COLOR_ONLY = 4
    # Each colour sample is the average of the picture over its pixel's footprint (a
    # photograph or a video downscaled by area, a supersampled render), not a point
    # sample as a game's renderer takes. A temporal method may then undo that box
    # faster (upscalers/temporal/params.py, ``area_precondition``): on point samples the
    # same step follows their aliasing.
    AREA_SAMPLES = 8


@dataclass(frozen=True)
class Camera:
    """Unjittered camera of a frame and of the frame before it."""

    view: F32Array  # (4, 4) world -> view
    proj: F32Array  # (4, 4) view -> clip
    prev_view: F32Array
    prev_proj: F32Array
    near: float
    far: float
    fov_y_deg: float

    @staticmethod
    def identity(near: float = 0.1, far: float = 100.0, fov_y_deg: float = 60.0) -> Camera:
        eye = np.eye(4, dtype=np.float32)
        return Camera(eye, eye, eye, eye, near, far, fov_y_deg)


@dataclass
class FrameMeta:
    """Everything in a slot header besides the pixel planes."""

    frame_id: int
    camera: Camera
    jitter: tuple[float, float] = (0.0, 0.0)
    flags: FrameFlags = FrameFlags.NONE
    # (STAGE_COUNT, 2) int64: monotonic ns, wall ns; see server/frames/timing.py
    stamps: I64Array = field(default_factory=new_stamps)
    # Last player input applied before this frame was rendered (0 = none).
    input_seq: int = 0
    # Game time the frame was rendered at, in microseconds (0 = unknown: a source
    # without a game clock, such as the load test's synthetic frames). With the frame
    # rate changing at run time the frame id alone no longer tells it; a benchmark
    # re-renders a received frame's ground truth from it. The game loop stamps every
    # tick (an X11 capture gets the loop's clock, which the application does not
    # follow); a predicted frame carries the time of the tick it stands for.
    game_time_us: int = 0


@dataclass
class RenderFrame:
    """A frame on ring R: render-size G-buffers plus metadata.

    Arrays may be read-only views of shared memory; never keep them past the
    slot's release.
    """

    color: U8Array  # (H, W, 3)
    depth: F32Array  # (H, W)
    motion: F32Array  # (H, W, 2)
    dynamic_mask: U8Array  # (H, W)
    meta: FrameMeta

    @property
    def size(self) -> Size:
        h, w = self.depth.shape
        return Size(w, h)


@dataclass
class DisplayFrame:
    """A frame on ring U: display-size sRGB color plus the same metadata."""

    color: U8Array  # (H, W, 3)
    meta: FrameMeta

    @property
    def size(self) -> Size:
        h, w, _ = self.color.shape
        return Size(w, h)
