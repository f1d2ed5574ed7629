"""Upscale your own images: one call for an image, one for a sequence.

    from upscalers import upscale_image
    big = upscale_image(image, 2, method="easu_rcas")   # (H, W, 3) uint8 RGB

Colour in: RGB (H, W, 3), uint8 in 0..255 or float32/float64 in [0, 1], checked
here with an error that says what was expected (``api_checks``). Colour out:
always a new uint8 (H, W, 3) array. Every method, spatial, temporal or network,
gets the same frame contract the stream gives it (``server/frames/frame.py``),
through the worker's own ``UpscalerHost`` (sanitizing, history resets), so a
picture upscaled here is the picture the stream would show.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np
import numpy.typing as npt

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size, U8Array
from upscalers.api_checks import (
    SizeOrScale,
    color_image,
    display_size,
    float_plane,
    jitter_pair,
    parse_size_or_scale,
)
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8

DEFAULT_METHOD = "easu_rcas"
# Without depth every pixel is at one depth: the renderer's sky (1.0), so no surface
# counts as newly uncovered and history is trusted wherever motion leads.
_NO_DEPTH = 1.0


def upscale_image(
    image: npt.NDArray[Any],
    size_or_scale: SizeOrScale,
    method: str = DEFAULT_METHOD,
    **options: Any,
) -> U8Array:
    """One image, upscaled: a new uint8 RGB (H', W', 3) array.

    ``image``: RGB (H, W, 3), uint8 0..255 or float32/float64 in [0, 1].
    ``size_or_scale``: a factor >= 1 (``2``, ``1.5``), or the output size as
    ``(width, height)``, a ``Size`` or ``"1280x720"``, at least the input's.
    ``method``: any name of ``upscalers.registry.available()``; ``options`` go to its
    constructor (e.g. ``sharpness=0.5`` for easu_rcas). A temporal method given one
    image has no history: it returns its first-frame reconstruction.
    """
    color = color_image(image)
    target = parse_size_or_scale(size_or_scale)
    render = Size(color.shape[1], color.shape[0])
    size = display_size(target, render)
    host = UpscalerHost(method, size, options)
    return to_uint8(host.upscale(_render_frame(color, 0, None, None, None)))


def upscale_sequence(
    frames: Iterable[npt.NDArray[Any]],
    size_or_scale: SizeOrScale,
    method: str = DEFAULT_METHOD,
    *,
    motion: Iterable[npt.NDArray[Any]] | None = None,
    jitter: Iterable[tuple[float, float]] | None = None,
    depth: Iterable[npt.NDArray[Any]] | None = None,
    area_samples: bool = False,
    detect_cuts: bool = True,
    **options: Any,
) -> Iterator[U8Array]:
    """Frames of a video in order, upscaled one by one: yields a uint8 (H', W', 3) each.

    ``frames`` as ``upscale_image`` takes an image. Temporal methods (``temporal``,
    the networks) build on the frames before, so they need to know how the content
    moved. Per frame, each optional:

    - ``motion``: float (H, W, 2) in input pixels; the content at pixel p of this
      frame was at p + motion in the frame before (the first frame's is unused).
      Without it every frame gets zero motion, which is right for a still camera
      over a still scene only: moving content smears or ghosts in a temporal method
      unless its motion is given.
    - ``jitter``: (jx, jy) in input pixels, each in [-0.5, 0.5]: this frame's pixel
      (i, j) was sampled at (i + 0.5 + jx, j + 0.5 + jy). A temporal method gathers
      detail above the input's resolution only from frames jittered like this
      (Halton 2, 3 as FSR 2 and DLSS do); without it, (0, 0).
    - ``depth``: float (H, W), NDC z in [0, 1] (1 is far); sharpens motion edges and
      finds newly uncovered surfaces. Without it, one depth everywhere.

    ``area_samples``: True when each input pixel is the average of the picture over its
    footprint (a photograph or video downscaled by area, a supersampled render), False
    (the default) for point samples, as a game's renderer takes them. The temporal
    method undoes the footprint's blur faster on area samples (on a held-out
    photograph with fine texture, +0.9 dB under a still camera); on point samples the
    same step follows their aliasing, so say True only when it is so.

    ``detect_cuts``: a temporal method starts its history afresh where the picture
    changes as a whole (a scene cut, ``upscalers/temporal/cut_detector.py``): without that it
    blends the picture before the cut into the frames after it. False trusts the
    sequence to have no cuts.

    Spatial methods upscale each frame alone. Non-finite depth or motion is replaced as in
    the stream (``upscalers/sanitize.py``). The method and ``size_or_scale`` are
    checked at the call; each frame when its turn comes (errors name the frame).
    """
    target = parse_size_or_scale(size_or_scale)
    # Built now, so that an unknown method or option fails at the call, not at the
    # first next(); the size is set per frame once the frames' size is known.
    host = UpscalerHost(method, Size(1, 1), options, detect_cuts=detect_cuts)
    flags = FrameFlags.AREA_SAMPLES if area_samples else FrameFlags.NONE
    return _sequence(host, frames, target, motion, jitter, depth, flags)


def _sequence(
    host: UpscalerHost,
    frames: Iterable[npt.NDArray[Any]],
    target: Size | float,
    motion: Iterable[npt.NDArray[Any]] | None,
    jitter: Iterable[tuple[float, float]] | None,
    depth: Iterable[npt.NDArray[Any]] | None,
    flags: FrameFlags,
) -> Iterator[U8Array]:
    extras = {
        "motion": None if motion is None else iter(motion),
        "jitter": None if jitter is None else iter(jitter),
        "depth": None if depth is None else iter(depth),
    }
    index = -1
    for index, image in enumerate(frames):
        color = color_image(image, f"frame {index}")
        render = Size(color.shape[1], color.shape[0])
        host.display_size = display_size(target, render)
        given = {name: _next(it, name, index) for name, it in extras.items()}
        yield to_uint8(
            host.upscale(
                _render_frame(color, index, given["motion"], given["jitter"], given["depth"], flags)
            )
        )
    for name, it in extras.items():
        if it is not None and next(it, _END) is not _END:
            raise ValueError(f"{name} has more entries than the {index + 1} frames")


_END = object()


def _next(it: Iterator[object] | None, name: str, index: int) -> object:
    if it is None:
        return None
    value = next(it, _END)
    if value is _END:
        raise ValueError(f"{name} has fewer entries than frames: none for frame {index}")
    return value


def _render_frame(
    color: U8Array,
    index: int,
    motion: object,
    jitter: object,
    depth: object,
    flags: FrameFlags = FrameFlags.NONE,
) -> RenderFrame:
    """The frame contract for one user frame: what is not given is what a still,
    unjittered camera over a flat scene would give."""
    h, w = color.shape[:2]
    return RenderFrame(
        color=color,
        depth=(
            np.full((h, w), _NO_DEPTH, np.float32)
            if depth is None
            else float_plane(depth, (h, w), "depth", index)
        ),
        motion=(
            np.zeros((h, w, 2), np.float32)
            if motion is None
            else float_plane(motion, (h, w, 2), "motion", index)
        ),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(
            frame_id=index,
            camera=Camera.identity(),
            jitter=(0.0, 0.0) if jitter is None else jitter_pair(jitter, index),
            # The first frame starts history afresh, as a scene cut does in the stream.
            flags=flags | (FrameFlags.RESET if index == 0 else FrameFlags.NONE),
        ),
    )
