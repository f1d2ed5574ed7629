"""What a cache policy sees of a frame, and the frame-delta measure (SMAPE).

The costly figures (SMAPE, mean motion, the finiteness scan) are computed on
first use, so a policy that does not look at them does not pay for them.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import numpy.typing as npt
import torch

Image = torch.Tensor | npt.NDArray[np.generic]


def all_finite(t: torch.Tensor) -> bool:
    """Whether ``t`` holds no NaN or Inf. A sum carries any NaN or Inf through and costs
    a fraction of an element-wise ``isfinite`` pass; only when the sum is not finite
    (bad values, or an overflow of huge finite ones) is the exact check run."""
    if bool(torch.isfinite(t.sum(dtype=torch.float32))):
        return True
    return bool(torch.isfinite(t).all())


def smape(current: Image, reference: Image) -> float:
    """ReFrame's frame delta: 2 mean|x - x_c| / mean(|x| + |x_c|), in [0, 2].

    Two all-zero images have changed by nothing: 0, not 0/0. Computed in float32
    (tensors or arrays, uint8 or float16 alike) so nothing overflows or rounds
    away the small differences."""
    if tuple(current.shape) != tuple(reference.shape):
        raise ValueError(
            f"SMAPE of different shapes {tuple(current.shape)} and {tuple(reference.shape)}"
        )
    if (
        isinstance(current, np.ndarray)
        and isinstance(reference, np.ndarray)
        and current.dtype == reference.dtype == np.uint8
    ):
        # Frame colour: exact integer sums, no float copies (about 3x faster).
        diff = np.abs(current.astype(np.int16) - reference.astype(np.int16))
        den_u = int(current.sum(dtype=np.int64)) + int(reference.sum(dtype=np.int64))
        return 0.0 if den_u == 0 else 2.0 * int(diff.sum(dtype=np.int64)) / den_u
    if isinstance(current, np.ndarray) and isinstance(reference, np.ndarray):
        xa = current.astype(np.float32, copy=False)
        ra = reference.astype(np.float32, copy=False)
        den = float(np.mean(np.abs(xa) + np.abs(ra)))
        return 0.0 if den == 0.0 else 2.0 * float(np.mean(np.abs(xa - ra))) / den
    x = torch.as_tensor(current).float()
    r = torch.as_tensor(reference).float()
    den_t = float((x.abs() + r.abs()).mean())
    return 0.0 if den_t == 0.0 else 2.0 * float((x - r).abs().mean()) / den_t


def mean_motion_px(motion: npt.NDArray[np.float32]) -> float:
    """Mean length of the (H, W, 2) motion vectors, in render pixels."""
    if motion.size == 0:
        return 0.0
    m = motion.astype(np.float32, copy=False)
    return float(np.mean(np.hypot(m[..., 0], m[..., 1])))


class FrameSignals:
    """One frame as a policy sees it.

    ``image`` is the frame's render-size colour (the "input image" whose SMAPE
    ReFrame thresholds) and ``reference`` the colour at the last refresh (None when
    there is none). The frame delta is taken on the colour, not on the whole
    network input: that input also carries the jitter offsets as constant planes,
    which change every frame by up to a pixel whatever the scene does, and they
    dominate its SMAPE (0.08 to 0.22 between frames of a still scene and of a fast
    yaw alike, measured on the U-Net's 22 input channels), so it would measure the
    Halton phase instead of the content. ``inputs`` is the network input, checked
    for non-finite values. ``since_refresh`` counts frames since the last refresh
    (1 on the frame right after it). ``cache_ready`` is whether the layer cache
    holds outputs that fit this frame (False on the first frame and after a
    resolution change)."""

    def __init__(
        self,
        *,
        inputs: torch.Tensor,
        image: Image,
        reference: Image | None,
        since_refresh: int,
        scene_cut: bool,
        cache_ready: bool,
        motion: npt.NDArray[np.float32] | None = None,
    ) -> None:
        self.inputs = inputs
        self.image = image
        self.reference = reference
        self.since_refresh = since_refresh
        self.scene_cut = scene_cut
        self.cache_ready = cache_ready
        self._motion = motion

    @cached_property
    def finite(self) -> bool:
        ok = all_finite(self.inputs)
        if ok and self._motion is not None:
            # A sum carries NaN/Inf through; the exact scan only when it is not finite.
            ok = bool(np.isfinite(self._motion.sum(dtype=np.float64))) or bool(
                np.isfinite(self._motion).all()
            )
        return ok

    @property
    def must_refresh(self) -> bool:
        """The rules no policy may overrule: first frame or cold cache, scene cut,
        non-finite input, nothing (or nothing of this size) to compare against."""
        return (
            not self.cache_ready
            or self.scene_cut
            or self.reference is None
            or tuple(self.reference.shape) != tuple(self.image.shape)
            or not self.finite
        )

    @cached_property
    def smape(self) -> float:
        """SMAPE of this frame's colour against the colour at the last refresh."""
        if self.reference is None or tuple(self.reference.shape) != tuple(self.image.shape):
            return float("inf")
        return smape(self.image, self.reference)

    @cached_property
    def mean_motion_px(self) -> float:
        """Mean motion-vector length of this frame (against the previous one), render px."""
        return 0.0 if self._motion is None else mean_motion_px(self._motion)
