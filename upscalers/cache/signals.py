"""What a cache policy sees of a frame, and the frame-delta measure (SMAPE).

The costly figures (SMAPE over the network input, mean motion) are computed on
first use, so a policy that does not look at them does not pay for them.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import numpy.typing as npt
import torch


def smape(current: torch.Tensor, reference: torch.Tensor) -> float:
    """ReFrame's frame delta: 2 mean|x - x_c| / mean(|x| + |x_c|), in [0, 2].

    Two all-zero tensors have changed by nothing: 0, not 0/0. Computed in float32
    so float16 inputs neither overflow nor lose the small differences."""
    if current.shape != reference.shape:
        raise ValueError(
            f"SMAPE of different shapes {tuple(current.shape)} and {tuple(reference.shape)}"
        )
    x = current.float()
    r = reference.float()
    den = float((x.abs() + r.abs()).mean())
    if den == 0.0:
        return 0.0
    return 2.0 * float((x - r).abs().mean()) / den


def mean_motion_px(motion: npt.NDArray[np.float32]) -> float:
    """Mean length of the (H, W, 2) motion vectors, in render pixels."""
    if motion.size == 0:
        return 0.0
    m = motion.astype(np.float32, copy=False)
    return float(np.mean(np.hypot(m[..., 0], m[..., 1])))


class FrameSignals:
    """One frame as a policy sees it.

    ``since_refresh`` counts frames since the last refresh (1 on the frame right
    after it). ``reference`` is the network input at the last refresh (None when
    there is none). ``cache_ready`` is whether the layer cache holds outputs that
    fit this frame (False on the first frame and after a resolution change)."""

    def __init__(
        self,
        *,
        inputs: torch.Tensor,
        reference: torch.Tensor | None,
        since_refresh: int,
        scene_cut: bool,
        cache_ready: bool,
        motion: npt.NDArray[np.float32] | None = None,
    ) -> None:
        self.inputs = inputs
        self.reference = reference
        self.since_refresh = since_refresh
        self.scene_cut = scene_cut
        self.cache_ready = cache_ready
        self._motion = motion

    @cached_property
    def finite(self) -> bool:
        ok = bool(torch.isfinite(self.inputs).all())
        if ok and self._motion is not None:
            ok = bool(np.isfinite(self._motion).all())
        return ok

    @property
    def must_refresh(self) -> bool:
        """The rules no policy may overrule: first frame or cold cache, scene cut,
        non-finite input, nothing (or nothing of this shape) to compare against."""
        return (
            not self.cache_ready
            or self.scene_cut
            or self.reference is None
            or self.reference.shape != self.inputs.shape
            or not self.finite
        )

    @cached_property
    def smape(self) -> float:
        """SMAPE of this frame's input against the input at the last refresh."""
        if self.reference is None:
            return float("inf")
        return smape(self.inputs, self.reference)

    @cached_property
    def mean_motion_px(self) -> float:
        """Mean motion-vector length of this frame (against the previous one), render px."""
        return 0.0 if self._motion is None else mean_motion_px(self._motion)
