"""What every grabber shares (grabbers.py registers them; each grabber module imports
only this): the frame type, the Grabber interface, the X pixel format conversion."""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

Frame = npt.NDArray[np.uint8]


class Grabber(Protocol):
    def screen_size(self) -> tuple[int, int]:
        """(width, height) of the screen when this grabber connected."""
        ...

    def grab_into(self, out: Frame) -> None:
        """Write the top-left ``out.shape[:2]`` pixels (within the screen) as RGB into ``out``."""
        ...

    def close(self) -> None: ...


def bgrx_to_rgb(src: Frame, out: Frame) -> None:
    """The X server's 32-bit little-endian pixels (B, G, R, pad) into RGB ``out``."""
    if out.flags.c_contiguous:
        # One pass, in place: OpenCV is about 4x numpy's strided assignment here.
        cv2.cvtColor(src, cv2.COLOR_BGRA2RGB, dst=out)
    else:
        out[...] = src[..., 2::-1]
