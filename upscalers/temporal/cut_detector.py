"""Scene cuts the frames do not flag, found before a temporal method blends across one.

The frame contract asks for ``FrameFlags.RESET`` at a cut, and the game sets it. A
video, a capture or an integration that forgets the flag does not: then the history
of the picture before the cut is blended into the one after it, held back only by
the neighbourhood clamp, and the first frames after the cut show a ghost of the old
picture (over photographs at 2x: 29.0 dB on the frame after an unflagged cut against
41.0 with the flag, still 4 dB short two frames later).

The test, as an encoder's scene-cut detection does it but with the motion the frame
carries: each sample is compared with the previous frame around where its motion
says the surface was. A sample that lies outside the previous frame's 3x3 range
there, or whose previous value lies outside this frame's 3x3 range (so a textured
picture giving way to a flat one counts too), by more than ``level`` 8-bit levels on
any channel, has changed beyond what sub-pixel motion, jitter or aliasing explain.
When that holds for at least ``fraction`` of the samples whose previous position is
on screen, the frame is a cut. A flash of light over the whole picture also counts;
it costs a reset, a few frames at the spatial method's quality, where a missed cut
costs a ghost.

Everything is at render size, one pass of a few cheap tensor operations.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from server.frames.frame import RenderFrame


@dataclass(frozen=True)
class CutParams:
    # How far past the neighbourhood's range a sample must lie to count as changed,
    # in 8-bit levels. Chosen with ``fraction`` on the game's scenes and the training
    # photographs (scripts, tests/test_cut_detector.py): see docs/upscalers.md, "Scene cuts".
    level: float = 24.0
    # The share of on-screen samples that must have changed.
    fraction: float = 0.2
    # Below this share of samples whose previous position is on screen, the camera
    # moved too far to judge (the temporal method trusts no history there anyway).
    min_on_screen: float = 0.25


# How many samples a frame is judged on (see _changed_share).
JUDGED_SAMPLES = 10_000


class CutDetector:
    """Remembers the last frame's colour and its 3x3 range at render size."""

    def __init__(self, params: CutParams | None = None) -> None:
        self.params = params or CutParams()
        # The last frame's (h, w, 3) uint8 colour, its 3x3 min and its 3x3 max.
        self._prev: tuple[torch.Tensor, ...] | None = None
        # The statistic of the last frame judged (None: not judged), for logs and tests.
        self.last_changed: float | None = None

    def reset(self) -> None:
        self._prev = None
        self.last_changed = None

    def observe(self, frame: RenderFrame) -> bool:
        """Remember ``frame`` and say whether it starts a new scene against the frame
        before (False for the first frame, after a size change, or when too little of
        the picture stays on screen to judge)."""
        # (h, w, 3) uint8 as the frame holds it, copied: the frame may be a view of a
        # ring slot that the next frame overwrites.
        color = torch.as_tensor(np.ascontiguousarray(frame.color)).clone()
        planes = (color, *_range_3x3(color))
        prev, self._prev = self._prev, planes
        self.last_changed = None
        if prev is None or prev[0].shape != color.shape:
            return False
        changed = self._changed_share(planes, prev, frame.motion)
        self.last_changed = changed
        return changed is not None and changed >= self.params.fraction

    def _changed_share(
        self, planes: tuple[torch.Tensor, ...], prev: tuple[torch.Tensor, ...], motion: np.ndarray
    ) -> float | None:
        h, w, _ = planes[0].shape
        # A grid of about JUDGED_SAMPLES samples is judged, not every one: the share
        # is then known to a fraction of a percent, and the cost stays the same at any
        # size (0.9 ms in all at 640x360, judging one sample in 16, on 2 cores).
        stride = max(1, int(math.sqrt(h * w / JUDGED_SAMPLES)))
        ys = torch.arange(0, h, stride)
        xs = torch.arange(0, w, stride)
        mv = torch.as_tensor(np.ascontiguousarray(motion[::stride, ::stride]))
        # Non-finite motion (the host sanitizes it first; a direct caller may not) is
        # taken as none, as the sanitizer does.
        mv = torch.nan_to_num(mv.to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
        # The surface at this sample's centre was at centre + motion (render pixels);
        # the 3x3 range absorbs the rounding and the jitter's sub-pixel shift.
        qx = xs.to(torch.float32).add_(0.5).add(mv[..., 0]).floor_()
        qy = ys.to(torch.float32).add_(0.5).unsqueeze(1).add(mv[..., 1]).floor_()
        on_screen = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
        count = int(on_screen.sum())
        if count == 0 or count < self.params.min_on_screen * on_screen.numel():
            return None
        idx = (qy.clamp_(0, h - 1) * w + qx.clamp_(0, w - 1)).long().view(-1)
        c0, lo0, hi0 = (t.view(h * w, 3).index_select(0, idx).to(torch.int16) for t in prev)
        c1, lo1, hi1 = (t[::stride, ::stride].reshape(-1, 3).to(torch.int16) for t in planes)
        # Distance of each value from the other frame's range, both ways round.
        past_then = torch.maximum(c1 - hi0, lo0 - c1)
        past_now = torch.maximum(c0 - hi1, lo1 - c0)
        distance = torch.maximum(past_then, past_now).amax(dim=1)
        changed = (distance > self.params.level) & on_screen.view(-1)
        return int(changed.sum()) / count


def _range_3x3(color: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per channel, the min and max of each sample's 3x3 neighbourhood of an (h, w, 3)
    image (edges: the samples that exist). Separable, from shifted views: max_pool2d
    took 11 ms at 640x360 on 2 cores, this takes well under one."""
    return _pass(_pass(color, 0, torch.minimum), 1, torch.minimum), _pass(
        _pass(color, 0, torch.maximum), 1, torch.maximum
    )


def _pass(x: torch.Tensor, dim: int, pick: Callable[..., torch.Tensor]) -> torch.Tensor:
    """Each element picked with its two neighbours along ``dim``."""
    n = x.shape[dim]
    out = x.clone()
    if n > 1:
        body = out.narrow(dim, 0, n - 1)
        pick(body, x.narrow(dim, 1, n - 1), out=body)
        tail = out.narrow(dim, 1, n - 1)
        pick(tail, x.narrow(dim, 0, n - 1), out=tail)
    return out
