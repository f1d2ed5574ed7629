"""The numba backend of Mesh Projection Estimation: host buffers around ``cpu_kernels``.

Same algorithm, options and outputs as the torch path in ``mpe.py`` (which stays
the reference and the CUDA path); see ``cpu_kernels`` for why it is faster on
the CPU. ``observe`` copies the rendered frame into buffers kept across frames
(sanitized depth, with dynamic pixels already replaced by the guessed
background, as the torch path does on every ``predict``); ``predict`` runs
vertices -> raster -> pixel stage -> pull-push fill of the 8-bit colour, reusing scratch buffers of
the frame size. Returned arrays are fresh, never scratch.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from numba import set_parallel_chunksize

from server.frames.frame import RenderFrame, Size
from upscalers.framegen import cpu_kernels as kernels
from upscalers.framegen.base import Prediction
from upscalers.framegen.geometry import Reprojection, pixel_space_matrices, z_at_infinity

if TYPE_CHECKING:
    from upscalers.framegen.mpe_options import MpeOptions

F32Array = npt.NDArray[np.float32]
_WORD_ROWS = sys.byteorder == "little"
_NO_WORDS = np.empty(0, np.uint32)


def _as_words(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint32]:
    """(H, W, 3) uint8 colour as its uint32 words, for kernels that move four pixels as
    three words; empty (the kernels go byte by byte) unless every row is whole words of
    contiguous little-endian memory."""
    if not (_WORD_ROWS and rgb.shape[1] % 4 == 0 and rgb.flags.c_contiguous):
        return _NO_WORDS
    return rgb.reshape(-1).view(np.uint32)


@contextmanager
def _one_block_at_a_time() -> Iterator[None]:
    """The raster and the pixel stage hand out their row blocks one at a time, not half the
    range per thread: on shared cores a parked thread then delays one block, not the frame.
    Only those two, the long ones: the fill's dozen block rows ran 2.3x slower handed out
    one at a time (numba's dynamic schedule), and the short passes gain nothing from it."""
    previous: int = set_parallel_chunksize(1)
    try:
        yield
    finally:
        set_parallel_chunksize(previous)


@dataclass
class HostFrame:
    """The cached frame in host memory, sanitized for the kernels."""

    packed: npt.NDArray[np.uint32]  # (H * W,) RGB as 0x00BBGGRR: one load per bilinear tap
    depth: F32Array  # (H, W) in [0, 1]; NaN -> 1; under dynamic objects the guessed background
    dynamic: npt.NDArray[np.bool_]  # (H, W)
    # ``depth`` with sky at the plane at infinity of ``z_inf`` (geometry.sky_as_direction),
    # made while sanitizing; NaN z_inf: not made yet (predict makes it).
    depth_eff: F32Array
    z_inf: float
    view: npt.NDArray[np.float64]
    proj: npt.NDArray[np.float64]
    frame_id: int
    size: Size


@dataclass
class _Scratch:
    """Per-size working buffers of one prediction."""

    zbuf: F32Array  # (H * W,) depth of the nearest triangle, inf where none
    u_map: F32Array  # (H * W,) its source position (0.5 where none)
    v_map: F32Array

    @staticmethod
    def allocate(w: int, h: int) -> _Scratch:
        return _Scratch(*(np.empty(h * w, np.float32) for _ in range(3)))


class HostMeshProjection:
    """Observe/predict of MPE on the CPU with compiled kernels (one cached frame)."""

    def __init__(self, options: MpeOptions) -> None:
        self.options = options
        self.frame: HostFrame | None = None
        self._scratch: _Scratch | None = None

    def reset(self) -> None:
        self.frame = None

    def observe(self, frame: RenderFrame) -> None:
        self._observe(frame)

    def predict(self, reproj: Reprojection) -> Prediction | None:
        """The predicted frame from the cached one (None when nothing is cached)."""
        return self._predict(reproj)

    def _observe(self, frame: RenderFrame) -> None:
        depth_src = np.asarray(frame.depth, dtype=np.float32)
        h, w = depth_src.shape
        color_src = np.asarray(frame.color, dtype=np.uint8)
        dynamic_src = np.asarray(frame.dynamic_mask)
        # The kernels index without bounds checks: refuse mismatched buffers here.
        if color_src.shape != (h, w, 3) or dynamic_src.shape != (h, w):
            raise ValueError(
                f"frame buffers disagree: colour {color_src.shape}, depth {(h, w)}, "
                f"dynamic mask {dynamic_src.shape}"
            )
        old = self.frame
        if old is not None and old.depth.shape == (h, w):
            # Only one frame is kept: reuse its buffers.
            packed, depth, dynamic, depth_eff = old.packed, old.depth, old.dynamic, old.depth_eff
        else:
            packed = np.empty(h * w, np.uint32)
            depth = np.empty((h, w), np.float32)
            dynamic = np.empty((h, w), np.bool_)
            depth_eff = np.empty((h, w), np.float32)
        cam = frame.meta.camera
        proj = np.asarray(cam.proj, dtype=np.float64)
        # NaN when there is none: predict then gets no reprojection anyway.
        z = z_at_infinity(proj)
        z_inf = math.nan if z is None else z
        n_dynamic = kernels.sanitize_frame(
            color_src,
            _as_words(color_src),
            depth_src,
            dynamic_src,
            packed,
            depth,
            dynamic,
            z_inf,
            depth_eff,
        )
        if n_dynamic:
            # Dynamic pixels carry the moving object's depth: the mesh wants the static
            # background behind them, guessed from the surroundings.
            kernels.pull_push_fill(depth.reshape(h, w, 1), dynamic, False)
            if z_inf == z_inf:
                kernels.sky_as_direction(depth, z_inf, depth_eff)
        self.frame = HostFrame(
            packed,
            depth,
            dynamic,
            depth_eff,
            z_inf,
            np.asarray(cam.view, dtype=np.float64),
            proj,
            frame.meta.frame_id,
            Size(w, h),
        )

    def _predict(self, reproj: Reprojection) -> Prediction | None:
        frame = self.frame
        if frame is None:
            return None
        o = self.options
        w, h = frame.size
        s = self._scratch
        if s is None or s.zbuf.size != w * h:
            s = self._scratch = _Scratch.allocate(w, h)
        if frame.z_inf != reproj.cached_z_inf:  # not made at observe (or NaN there)
            kernels.sky_as_direction(frame.depth, reproj.cached_z_inf, frame.depth_eff)
            frame.z_inf = reproj.cached_z_inf
        th, tw = -(-h // o.tile), -(-w // o.tile)
        verts = np.empty((6, th + 2, tw + 2), np.float64)
        kernels.mesh_vertices(
            frame.depth,
            frame.depth_eff,
            frame.dynamic,
            np.ascontiguousarray(reproj.forward, dtype=np.float64),
            o.tile,
            o.tensile,
            o.tensile_threshold_px,
            verts,
        )
        planes = np.empty((2 * (th + 1) * (tw + 1), 3, 3), np.float32)
        max_bbox = max(16, int(o.max_bbox_share * w * h))
        with _one_block_at_a_time():
            kernels.rasterize(verts, w, h, max_bbox, s.zbuf, s.u_map, s.v_map, planes)
        fm, gm = (m.astype(np.float32) for m in pixel_space_matrices(reproj, w, h))
        depth = np.empty((h, w), np.float32)
        holes = np.empty(h * w, np.bool_)
        no_colour = np.empty(h * w, np.bool_)
        color = np.empty((h, w, 3), np.uint8)
        with _one_block_at_a_time():
            kernels.pixel_stage(
                s.zbuf,
                s.u_map,
                s.v_map,
                frame.depth_eff.reshape(-1),
                frame.dynamic.reshape(-1),
                frame.packed,
                fm,
                gm,
                reproj.cached_z_inf,
                reproj.new_z_inf,
                o.shear,
                o.shear_tolerance,
                o.shear_min_shift_px,
                o.shear_iterations,
                color,
                _as_words(color),
                depth,
                holes,
                no_colour,
            )
        kernels.pull_push_fill(color, no_colour.reshape(h, w), True)
        return Prediction(
            color, holes.reshape(h, w), depth, frame.frame_id, no_colour.reshape(h, w)
        )


_WARM = False


def warm_up(options: MpeOptions) -> float:
    """Compile (or load from the on-disk cache) every kernel on a tiny frame; seconds spent.

    Runs once per process, so the first real predicted frame is not late.
    """
    global _WARM
    if _WARM:
        return 0.0
    from server.frames.frame import Camera, FrameMeta

    t0 = time.perf_counter()
    w, h = 24, 14
    f32 = np.float32
    eye = np.eye(4, dtype=f32)
    proj = np.array(
        [[1.0, 0, 0, 0], [0, 1.5, 0, 0], [0, 0, -1.001, -0.2], [0, 0, -1.0, 0]], dtype=f32
    )
    depth = np.full((h, w), 0.9, f32)
    depth[:, w // 2 :] = 1.0
    dynamic = np.zeros((h, w), np.uint8)
    dynamic[2:5, 2:5] = 1
    cam = Camera(eye, proj, eye, proj, 0.1, 200.0, 60.0)
    frame = RenderFrame(
        np.zeros((h, w, 3), np.uint8), depth, np.zeros((h, w, 2), f32), dynamic, FrameMeta(0, cam)
    )
    host = HostMeshProjection(options)
    host.observe(frame)
    moved = eye.copy()
    moved[0, 3] = 0.05
    reproj = Reprojection.between(eye, proj, moved, proj)
    if reproj is not None:
        host.predict(reproj)
    _WARM = True
    return time.perf_counter() - t0
