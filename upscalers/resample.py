"""Classic resamplers on the uint8 colour plane: nearest, bilinear, bicubic.

They run torch's separable uint8 resampler on the slot's HWC bytes (which are
already a channels-last NCHW tensor, so no transpose copy): 3-4x faster than the
float path on one core, and what a video pipeline would use.

Bilinear runs OpenCV's ``resize`` instead by default: the same images (within one
level everywhere, borders included: both clamp the sample position to the edge
pixel centre, and OpenCV's 11-bit fixed-point weights round differently) in
about a quarter of the time (0.6 against 2.4 ms at 640x360 -> 1280x720 on 2
cores). Nearest and bicubic stay on torch: OpenCV's cubic is a = -0.75 (up to
16 levels from Catmull-Rom on a game frame), and its exact nearest breaks the
ties of a 1.5x scale the other way (a whole pixel off in a third of the rows).
These upscalers read the slot on the CPU, so there is no CUDA path to keep.
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
from upscalers.cv_resample import cv_resize

# "auto" takes the library resampler where it gives the same images faster; "torch"
# keeps F.interpolate (the reference, and what the eval's METHOD+torch times).
ResampleBackend = Literal["auto", "torch"]
RESAMPLE_BACKENDS: tuple[ResampleBackend, ...] = ("auto", "torch")


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


class NearestUpscaler(_TorchResampler):
    name = "nearest"
    mode = "nearest-exact"


class BilinearUpscaler(_TorchResampler):
    """Bilinear with half-pixel centres; OpenCV's resize unless ``backend="torch"``."""

    name = "bilinear"
    mode = "bilinear"

    def __init__(self, backend: ResampleBackend = "auto") -> None:
        if backend not in RESAMPLE_BACKENDS:
            raise ValueError(
                f"backend must be one of {', '.join(RESAMPLE_BACKENDS)}, got {backend!r}"
            )
        self.backend: str = "opencv" if backend == "auto" else "torch"

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        if self.backend == "opencv":
            return cv_resize(frame.color, display_size, cv2.INTER_LINEAR)
        return super().upscale(frame, display_size)


class BicubicUpscaler(_TorchResampler):
    """Keys cubic with a = -0.5 (Catmull-Rom, as PIL), via torch's uint8 path.

    torch's float bicubic uses a = -0.75 and is 9x slower on one core; the
    uint8 kernel is the one selected by ``antialias=True``, which for
    upsampling changes nothing but the kernel parameter.
    """

    name = "bicubic"
    mode = "bicubic"
    antialias = True
