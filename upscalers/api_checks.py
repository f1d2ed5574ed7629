"""What ``upscale_image`` and ``upscale_sequence`` accept, checked at the edge.

One colour convention for users: RGB, (H, W, 3), either uint8 in 0..255 or
float32/float64 in [0, 1]. Anything else fails here with a message that says
what was expected and what came, never deeper down as a wrong picture: a float
image in 0..255 would otherwise clip to white, a (3, H, W) one would be read as
an image three pixels high. Inside, every method then gets the frame contract's
sRGB uint8 and converts to whatever range it computes in.

Standard numpy only; no torch, so the checks cost nothing beside the methods.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from server.frames.frame import F32Array, Size, U8Array

# A float colour may stray this far outside [0, 1] (half a level: it still rounds to
# 0 or 255), so values from float arithmetic such as 1.0000001 pass and 0..255 fails.
RANGE_SLACK = 0.5 / 255.0
FLOAT_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
# A scale or size as the API takes it: a factor >= 1, (width, height), Size or "WxH".
SizeOrScale = float | int | np.floating[Any] | np.integer[Any] | tuple[int, int] | Size | str


def _describe(value: object) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    return f"a {type(value).__module__}.{type(value).__qualname__}"


def _shape_hint(shape: tuple[int, ...]) -> str:
    if len(shape) == 2 or (len(shape) == 3 and shape[2] == 1):
        return "; a grey image: repeat it, np.repeat(image.reshape(h, w, 1), 3, axis=2)"
    if len(shape) == 3 and shape[2] == 4:
        return "; RGBA: drop the alpha channel, image[..., :3]"
    if len(shape) == 3 and shape[0] in (1, 3, 4):
        return "; channels first (C, H, W)? pass image.transpose(1, 2, 0)"
    return ""


def color_image(image: object, what: str = "image") -> U8Array:
    """``image`` as the frame contract's sRGB uint8 (H, W, 3) (uint8 input: itself).

    TypeError for something that is not an array of a colour dtype, ValueError for a
    wrong shape, an empty image, or float values that are not finite or not in [0, 1].
    """
    if not isinstance(image, np.ndarray):
        hint = " (a torch tensor: image.cpu().numpy(); a PIL image: np.asarray(image))"
        raise TypeError(f"{what} must be a numpy array (H, W, 3), got {_describe(image)}{hint}")
    shape = tuple(int(n) for n in image.shape)
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(
            f"{what} must be RGB of shape (H, W, 3), got shape {shape}{_shape_hint(shape)}"
        )
    if shape[0] == 0 or shape[1] == 0:
        raise ValueError(f"{what} must have at least one pixel, got shape {shape}")
    if image.dtype == np.uint8:
        # A view such as image[..., ::-1] (BGR to RGB) has negative or gapped strides,
        # which torch.from_numpy refuses; the ring's slots, which methods are written
        # for, are contiguous. A contiguous image is passed on without a copy.
        contiguous: U8Array = np.ascontiguousarray(image)
        return contiguous
    if image.dtype not in FLOAT_DTYPES:
        raise TypeError(
            f"{what} must be uint8 in 0..255 or float32/float64 in [0, 1], got dtype {image.dtype}"
        )
    # min and max propagate a NaN and show an Inf: no mask of the whole image needed.
    lo, hi = float(image.min()), float(image.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"float {what} must be finite, got NaN or Inf values")
    if lo < -RANGE_SLACK or hi > 1.0 + RANGE_SLACK:
        hint = " (it looks like 0..255: divide by 255 or pass uint8)" if hi > 2.0 else ""
        raise ValueError(f"float {what} must be in [0, 1], got values from {lo:g} to {hi:g}{hint}")
    scaled = np.multiply(image, 255.0, dtype=np.float64)
    return np.rint(np.clip(scaled, 0.0, 255.0, out=scaled)).astype(np.uint8)


def parse_size_or_scale(size_or_scale: object) -> Size | float:
    """A display Size, or a scale factor >= 1; TypeError/ValueError say the forms."""
    forms = "a scale >= 1 (2, 1.5), a size (width, height) or 'WIDTHxHEIGHT'"
    if isinstance(size_or_scale, bool) or size_or_scale is None:
        raise TypeError(f"size_or_scale must be {forms}, got {size_or_scale!r}")
    if isinstance(size_or_scale, (int, float, np.integer, np.floating)):
        scale = float(size_or_scale)
        if not math.isfinite(scale) or scale < 1.0:
            raise ValueError(f"scale must be a finite number >= 1 (upscaling only), got {scale}")
        return scale
    if isinstance(size_or_scale, str):
        return Size.parse(size_or_scale)
    if isinstance(size_or_scale, Sequence) and len(size_or_scale) == 2:
        w, h = size_or_scale
        if all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in (w, h)):
            if w > 0 and h > 0:
                return Size(int(w), int(h))
            raise ValueError(f"size must be positive (width, height), got {(w, h)}")
    raise TypeError(f"size_or_scale must be {forms}, got {size_or_scale!r}")


def display_size(target: Size | float, render: Size) -> Size:
    """The output size for an input of size ``render`` (ValueError below the input)."""
    if isinstance(target, float):
        return render.scaled(target)
    if target.width < render.width or target.height < render.height:
        raise ValueError(
            f"size {target} (width x height) is smaller than the image, {render}: "
            "these methods only upscale"
        )
    return target


def float_plane(value: object, shape: tuple[int, ...], what: str, frame_index: int) -> F32Array:
    """A float32 plane of exactly ``shape`` (depth (H, W), motion (H, W, 2)).

    Its values are not checked here: NaN, Inf or absurd motion are replaced by the
    worker's own sanitizer (upscalers/sanitize.py), as they would be in the stream."""
    where = f"{what} of frame {frame_index}"
    if not isinstance(value, np.ndarray):
        raise TypeError(f"{where} must be a numpy array {shape}, got {_describe(value)}")
    if value.shape != shape:
        raise ValueError(f"{where} must have shape {shape} (the frame's), got {value.shape}")
    if not np.issubdtype(value.dtype, np.floating):
        raise TypeError(f"{where} must be float, got dtype {value.dtype}")
    out: F32Array = np.ascontiguousarray(value, dtype=np.float32)  # torch refuses odd strides
    return out


def jitter_pair(value: object, frame_index: int) -> tuple[float, float]:
    """(jx, jy) in render pixels, each in [-0.5, 0.5] (the frame contract's)."""
    where = f"jitter of frame {frame_index}"
    pair = list(value) if isinstance(value, (Sequence, np.ndarray)) else []
    try:
        if len(pair) != 2 or isinstance(value, str):
            raise TypeError
        jx, jy = float(pair[0]), float(pair[1])
    except (TypeError, ValueError):
        raise TypeError(f"{where} must be two numbers (jx, jy), got {value!r}") from None
    if not (abs(jx) <= 0.5 and abs(jy) <= 0.5):
        raise ValueError(
            f"{where} must be in render pixels, each in [-0.5, 0.5], got ({jx:g}, {jy:g})"
        )
    return jx, jy
