"""Tuning of the temporal upscaler, shared by its torch (temporal.py) and numba
(temporal_cpu.py) paths."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TemporalParams:
    """Tuning of the accumulation; defaults were chosen on the reference game scenes."""

    # Accumulated sample weight is capped here: alpha >= about 1 / (max_weight + 1).
    max_weight: float = 24.0
    # Sample weight: Gaussian of the nearest sample's distance from the display pixel
    # centre, in display pixels; floored so history never freezes.
    sample_sigma: float = 0.35
    min_sample_weight: float = 0.01
    # Disocclusion: history is dropped where the farthest previous depth around the
    # reprojected position is nearer than this surface by more than this fraction.
    depth_tolerance: float = 0.05
    # History weight kept per frame on moving objects (partial trust, never full).
    dynamic_keep: float = 0.5
    # Current-frame reconstruction: bilinear between the jittered samples with the
    # fraction pushed towards the nearest sample (1 = bilinear, larger = crisper).
    reconstruct_sharpness: float = 3.0
    # Unsharp amount applied to the render samples (4-neighbour cross): the game picks
    # texture mips for the render size, accumulation alone cannot undo that blur.
    presharpen: float = 0.75
    # History fetch: bilinear plus a Catmull-Rom correction of each plane (_sharpen_fetch);
    # the gain scales the correction (1 = Catmull-Rom).
    history_catmull_rom: bool = True
    history_sharpen_gain: float = 1.0
    # A reset (first frame, scene cut) starts the history from a Lanczos-2 reconstruction
    # of the frame's own samples at their jittered positions, worth this much accumulated
    # sample weight in that frame's blend (not carried on): the first frames after a cut
    # are as sharp as a spatial upscaler instead of the sparse jittered samples alone.
    reset_weight: float = 1.0
