"""Make a frame safe to upscale: no NaN or Inf reaches a method or its history.

The ring's colour plane is uint8 and cannot hold them; depth, motion and the
camera floats can (a driver bug, a division by zero in a shader). Values are
replaced, never the whole frame dropped: depth -> 1.0 (sky, "nothing to
reproject"), motion -> 0, jitter -> 0. The slot itself is read-only, so a frame
with bad values is copied; a clean frame (the normal case) costs two
``isfinite`` scans and no copy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from server.frame import RenderFrame

# Larger motion than this many frame widths is not motion, it is garbage.
_MAX_MOTION_FRAMES = 4.0


@dataclass(frozen=True)
class SanitizeReport:
    depth_fixed: int = 0
    motion_fixed: int = 0
    meta_fixed: int = 0

    @property
    def total(self) -> int:
        return self.depth_fixed + self.motion_fixed + self.meta_fixed


def sanitize_frame(frame: RenderFrame) -> tuple[RenderFrame, SanitizeReport]:
    depth, motion, meta = frame.depth, frame.motion, frame.meta
    depth_fixed = motion_fixed = meta_fixed = 0

    depth_ok = np.isfinite(depth)
    if not depth_ok.all():
        depth_fixed = int(depth.size - np.count_nonzero(depth_ok))
        depth = np.where(depth_ok, depth, np.float32(1.0)).astype(np.float32)
    limit = _MAX_MOTION_FRAMES * max(frame.size)
    motion_ok = np.isfinite(motion)
    if not motion_ok.all() or (motion_ok.size and np.abs(motion).max() > limit):
        bad = ~motion_ok | (np.abs(np.where(motion_ok, motion, 0)) > limit)
        motion_fixed = int(np.count_nonzero(bad))
        motion = np.where(bad, np.float32(0.0), motion).astype(np.float32)

    jitter = meta.jitter
    if not all(math.isfinite(j) for j in jitter):
        meta_fixed += 1
        jitter = (0.0, 0.0)
    if meta_fixed:
        meta = replace(meta, jitter=jitter)

    report = SanitizeReport(depth_fixed, motion_fixed, meta_fixed)
    if report.total == 0:
        return frame, report
    return replace(frame, depth=depth, motion=motion, meta=meta), report
