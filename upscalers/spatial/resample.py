"""Classic resamplers on the uint8 colour plane: nearest, bilinear, bicubic.

They run torch's separable uint8 resampler on the slot's HWC bytes (which are
already a channels-last NCHW tensor, so no transpose copy): 3-4x faster than the
float path on one core, and what a video pipeline would use.

Where OpenCV's ``resize`` gives the same images it runs instead (``upcast bench
resample`` compares them on game frames and noise, borders included):

- bilinear, always: within one level everywhere (both clamp the sample position
  to the edge pixel centre; OpenCV's 11-bit fixed-point weights round
  differently), 3.9-5.5x as fast at 1.5x, 2x and 3x to 1280x720 on 2 cores;
- nearest, when the display size is a whole multiple (up to 8) of the render
  size on both axes: the same bits (no output centre falls on an input pixel
  edge, so no tie to break), 8x as fast at 2x. At other scales OpenCV's exact
  nearest breaks ties the other way (at 1.5x another source pixel for 14 % of a
  noise image's pixels, 7 % of a game frame's off by more than a level), so
  torch keeps them.

Bicubic stays on torch: OpenCV's cubic is a = -0.75, 16 levels and more from
Catmull-Rom on a game frame (it is ``cv_cubic``, a method of its own).
``backend="torch"`` keeps F.interpolate for all sizes. These upscalers read the
slot on the CPU, so there is no CUDA path to keep.
"""

from __future__ import annotations

import warnings
from typing import ClassVar, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from server.frames.frame import RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.spatial.cv_resample import cv_resize

# "auto" takes the library resampler where it gives the same images faster; "torch"
# keeps F.interpolate (the reference, and what the eval's METHOD+torch times).
ResampleBackend = Literal["auto", "torch"]
RESAMPLE_BACKENDS: tuple[ResampleBackend, ...] = ("auto", "torch")
MAX_NEAREST_FACTOR = 8


def color_as_nchw(color: np.ndarray) -> torch.Tensor:
    """(1, 3, H, W) uint8 tensor sharing memory with an (H, W, 3) array (read-only OK)."""
    with warnings.catch_warnings():
        # Views of a READING slot are read-only by design; torch warns on any such array
        # even though nothing here writes to it.
        warnings.simplefilter("ignore", UserWarning)
        hwc = torch.from_numpy(color)
    return hwc.permute(2, 0, 1).unsqueeze(0)


class _TorchResampler(Upscaler):
    mode: ClassVar[str]
    antialias: ClassVar[bool] = False

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        x = color_as_nchw(frame.color)
        out = F.interpolate(
            x,
            size=(display_size.height, display_size.width),
            mode=self.mode,
            antialias=self.antialias,
            **({} if self.mode.startswith("nearest") else {"align_corners": False}),
        )
        return out[0]


class _LibraryWhereSame(_TorchResampler):
    """Runs OpenCV's ``interpolation`` where it gives torch's images, else torch."""

    interpolation: ClassVar[int]

    def __init__(self, backend: ResampleBackend = "auto") -> None:
        if backend not in RESAMPLE_BACKENDS:
            raise ValueError(
                f"backend must be one of {', '.join(RESAMPLE_BACKENDS)}, got {backend!r}"
            )
        self.backend: str = "opencv" if backend == "auto" else "torch"

    def library_serves(self, render: Size, display: Size) -> bool:
        return True

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        if self.backend == "opencv" and self.library_serves(frame.size, display_size):
            return cv_resize(frame.color, display_size, self.interpolation)
        return super().upscale(frame, display_size)


class NearestUpscaler(_LibraryWhereSame):
    """Nearest with half-pixel centres (torch's nearest-exact); OpenCV's exact nearest
    at whole-multiple scales unless ``backend="torch"``."""

    name = "nearest"
    mode = "nearest-exact"
    interpolation = cv2.INTER_NEAREST_EXACT

    def library_serves(self, render: Size, display: Size) -> bool:
        # Checked for every width 1..4096 and every third height to 2048 at 1x to 8x: the
        # same bits. Larger factors are left to torch: OpenCV's 16-bit fixed-point step
        # drifts with the output coordinate, and 8x is where the check stopped.
        return all(
            big % small == 0 and 1 <= big // small <= MAX_NEAREST_FACTOR
            for big, small in zip(display, render, strict=True)
        )


class BilinearUpscaler(_LibraryWhereSame):
    """Bilinear with half-pixel centres; OpenCV's resize unless ``backend="torch"``."""

    name = "bilinear"
    mode = "bilinear"
    interpolation = cv2.INTER_LINEAR


class BicubicUpscaler(_TorchResampler):
    """Keys cubic with a = -0.5 (Catmull-Rom, as PIL), via torch's uint8 path.

    torch's float bicubic uses a = -0.75 and is 9x slower on one core; the
    uint8 kernel is the one selected by ``antialias=True``, which for
    upsampling changes nothing but the kernel parameter.
    """

    name = "bicubic"
    mode = "bicubic"
    antialias = True
