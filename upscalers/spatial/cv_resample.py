"""OpenCV's resize as upscalers: the library baselines (cubic, Lanczos-4, area).

They run ``cv2.resize`` on the slot's (H, W, 3) uint8 bytes, OpenCV's
fixed-point SIMD code, and return its result as the (3, H, W) uint8 view that
ring U takes (``quantize_into`` copies it once, as it does the torch
resamplers'). They are not the project's own resamplers under other names:

- ``cv_cubic`` is Keys cubic with a = -0.75 (OpenCV's choice) where ``bicubic``
  uses a = -0.5 (Catmull-Rom, as PIL): sharper, with more overshoot; up to 16
  levels apart on a game frame at 2x.
- ``cv_lanczos4`` is an 8x8 windowed sinc where ``lanczos2`` is 4x4.
- ``cv_area`` weighs input pixels by their overlap with the output pixel: a box
  filter, which at integer scales repeats pixels like ``nearest``.

Edges repeat the border pixel (``BORDER_REPLICATE``, fixed inside ``resize``).
OpenCV runs on its own thread pool; ``server.ops.cpu_threads`` gives it the same
budget as torch.
"""

from __future__ import annotations

from typing import ClassVar

import cv2
import numpy as np
import numpy.typing as npt
import torch

from server.frames.frame import RenderFrame, Size
from upscalers.base import Upscaler


def cv_resize(color: npt.NDArray[np.uint8], size: Size, interpolation: int) -> torch.Tensor:
    """(3, H, W) uint8 tensor of ``cv2.resize`` of an (h, w, 3) uint8 image to ``size``.

    The result is a channels-last view of OpenCV's new array, so no transpose copy."""
    out = cv2.resize(color, (size.width, size.height), interpolation=interpolation)
    # OpenCV drops a last axis of length 1; three channels always come back as three.
    return torch.from_numpy(out).permute(2, 0, 1)


class _CvResampler(Upscaler):
    interpolation: ClassVar[int]

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        return cv_resize(frame.color, display_size, self.interpolation)


class CvCubicUpscaler(_CvResampler):
    name = "cv_cubic"
    interpolation = cv2.INTER_CUBIC


class CvLanczos4Upscaler(_CvResampler):
    name = "cv_lanczos4"
    interpolation = cv2.INTER_LANCZOS4


class CvAreaUpscaler(_CvResampler):
    name = "cv_area"
    interpolation = cv2.INTER_AREA
