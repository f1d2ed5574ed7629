"""Frame sequences from one photograph, with exact motion and a box-filtered truth.

A camera over a flat photograph is an affine map per frame from display
coordinates (continuous, pixel (i, j) centred at (i + 0.5, j + 0.5)) to source
pixels: ``source = a * display + b``. Every pixel is a box average over its
footprint in the source: a display pixel's for the truth, a render pixel's,
shifted by the frame's Halton jitter, for the render. So the render is what a
renderer with one box-filtered sample per pixel would produce, and the motion
vectors follow from the maps alone: the surface at render position p (its
unjittered centre) maps to the source and back through the previous frame's
map; ``motion = p_prev - p`` as the frame contract has it (prev = p + motion).
Depth is constant (a flat picture), no pixel is dynamic.

Kinds: ``first`` (one frame, RESET), ``pan`` (diagonal, a fraction of a render
pixel a frame), ``zoom`` (about the centre; the motion field is radial), ``still``
(the camera does not move; only the jitter differs) and ``cut`` (a pan over
another picture, then RESET and a pan over this one from the middle on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from server.game.render.transforms import jitter_offset, jitter_phase_count

F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

KINDS = ("first", "pan", "zoom", "still", "cut")
# Source pixels per display pixel at most: two makes each display pixel a box over
# four photograph pixels, so the truth holds detail the render cannot.
MAX_SOURCE_PER_DISPLAY = 2.0
PAN_PER_FRAME = (0.61, 0.37)  # display px: a diagonal, a fraction of a render pixel at 2x
ZOOM_PER_FRAME = 1.01  # magnification factor per frame
# Display pixels kept free around the view so pans and zooms stay inside the picture.
PAD = 16


@dataclass(frozen=True)
class View:
    """source = a * display + b, per axis (the source is not stretched: one ``a``)."""

    a: float
    bx: float
    by: float


@dataclass
class Sequence:
    kind: str
    image: str
    jittered: list[RenderFrame]  # for temporal methods
    unjittered: list[RenderFrame]  # for spatial methods, as the game sends them
    truth: list[U8]
    cut: int | None  # index of the frame after the cut

    def frames_for(self, temporal: bool) -> list[RenderFrame]:
        return self.jittered if temporal else self.unjittered


def area_sample(src: F32, a_x: float, a_y: float, b_x: float, b_y: float, out: Size) -> F32:
    """Output pixel u (continuous) covers source ``a * u + b`` per axis: the box average
    of its footprint (``area_sample_affine`` with a diagonal map)."""
    return area_sample_affine(src, np.diag([a_x, a_y]), np.array([b_x, b_y]), out)


def area_sample_affine(src: F32, a: F64, b: F64, out: Size) -> F32:
    """Output pixel u (continuous) covers source ``a @ u + b``: the box average of its
    footprint, sampled k x k times (k >= the footprint's extent in source pixels,
    bilinear between source pixels) and averaged; a rotated footprint is covered by
    the rotated k x k grid."""
    extent = float(np.abs(a).sum(axis=1).max())
    k = max(1, math.ceil(extent - 1e-6))
    sub = a / k
    # OpenCV's pixel x sits at continuous x + 0.5 on both sides of the map.
    offset = a @ np.array([0.5 / k, 0.5 / k]) + b - 0.5
    m = np.array([[sub[0, 0], sub[0, 1], offset[0]], [sub[1, 0], sub[1, 1], offset[1]]], np.float32)
    big = cv2.warpAffine(
        src,
        m,
        (out.width * k, out.height * k),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )
    if k == 1:
        return np.asarray(big, dtype=np.float32)
    return np.asarray(
        cv2.resize(big, (out.width, out.height), interpolation=cv2.INTER_AREA), dtype=np.float32
    )


def source_scale(src_size: Size, display: Size) -> float:
    """Source pixels per display pixel: at most MAX_SOURCE_PER_DISPLAY, less where the
    picture (minus the padding) is smaller."""
    return min(
        MAX_SOURCE_PER_DISPLAY,
        src_size.width / (display.width + 2 * PAD),
        src_size.height / (display.height + 2 * PAD),
    )


def views(kind: str, frames: int, src_size: Size, display: Size) -> list[View]:
    """The camera of each frame, centred on the picture over the sequence."""
    d = source_scale(src_size, display)
    cs = (src_size.width / 2, src_size.height / 2)
    cd = (display.width / 2, display.height / 2)
    if kind == "first":
        frames = 1
    out = []
    for t in range(frames):
        if kind == "zoom":
            # Zooming in from the widest view, which fits the picture.
            a = d / ZOOM_PER_FRAME**t
            out.append(View(a, cs[0] - a * cd[0], cs[1] - a * cd[1]))
            continue
        moving = kind in ("pan", "cut")
        sx, sy = (v * (t - (frames - 1) / 2) if moving else 0.0 for v in PAN_PER_FRAME)
        out.append(View(d, cs[0] + d * (sx - cd[0]), cs[1] + d * (sy - cd[1])))
    return out


def motion_field(view: View, prev: View | None, render: Size, display: Size) -> F32:
    """(h, w, 2) render pixels: the unjittered centre p through this frame's map to the
    source and back through the previous frame's; zero without a previous frame."""
    motion = np.zeros((render.height, render.width, 2), np.float32)
    if prev is None:
        return motion
    for axis, (n, s, b, pb) in enumerate(
        (
            (render.width, display.width / render.width, view.bx, prev.bx),
            (render.height, display.height / render.height, view.by, prev.by),
        )
    ):
        p = np.arange(n, dtype=np.float64) + 0.5
        source = view.a * s * p + b
        p_prev = (source - pb) / (prev.a * s)
        delta = (p_prev - p).astype(np.float32)
        if axis == 0:
            motion[:, :, 0] = delta[None, :]
        else:
            motion[:, :, 1] = delta[:, None]
    return motion


def _to_u8(image: F32) -> U8:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _render(src: F32, view: View, render: Size, display: Size, jitter: tuple[float, float]) -> U8:
    sx, sy = display.width / render.width, display.height / render.height
    ax, ay = view.a * sx, view.a * sy
    return _to_u8(
        area_sample(src, ax, ay, view.bx + ax * jitter[0], view.by + ay * jitter[1], render)
    )


def build_sequence(
    kind: str,
    image: str,
    src: U8,
    other: U8,
    display: Size,
    scale: float,
    frames: int,
) -> Sequence:
    """Frames of ``kind`` over ``src`` (RGB uint8); ``other`` is the picture before a cut."""
    if kind not in KINDS:
        raise ValueError(f"unknown sequence kind {kind!r}; known: {', '.join(KINDS)}")
    render = display.scaled(1 / scale)
    phases = jitter_phase_count(scale)
    count = 1 if kind == "first" else frames
    cut = count // 2 if kind == "cut" else None
    pictures = [src.astype(np.float32), other.astype(np.float32)]
    sizes = [Size(p.shape[1], p.shape[0]) for p in pictures]
    cams = [views(kind, count, sz, display) for sz in sizes]
    seq = Sequence(kind, image, [], [], [], cut)
    for t in range(count):
        which = 1 if cut is not None and t < cut else 0
        picture, view = pictures[which], cams[which][t]
        reset = t == 0 or t == cut
        prev = None if reset else cams[which][t - 1]
        motion = motion_field(view, prev, render, display)
        # Every sample is the area average over its footprint (area_sample), as a
        # photograph or video downscaled by area is: the frames say so.
        flags = FrameFlags.AREA_SAMPLES | (FrameFlags.RESET if reset else FrameFlags.NONE)
        jitter = jitter_offset(t, phases)
        for target, jit in ((seq.jittered, jitter), (seq.unjittered, (0.0, 0.0))):
            target.append(
                RenderFrame(
                    color=_render(picture, view, render, display, jit),
                    depth=np.full((render.height, render.width), 0.5, np.float32),
                    motion=motion,
                    dynamic_mask=np.zeros((render.height, render.width), np.uint8),
                    meta=FrameMeta(t, Camera.identity(), jit, flags),
                )
            )
        seq.truth.append(_to_u8(area_sample(picture, view.a, view.a, view.bx, view.by, display)))
    return seq
