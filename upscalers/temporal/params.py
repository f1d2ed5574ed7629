"""Tuning of the temporal upscaler, shared by its torch (temporal.py) and numba
(temporal_cpu.py) paths."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TemporalParams:
    """Tuning of the accumulation; defaults were chosen on the reference game scenes."""

    # Accumulated sample weight is capped here: alpha >= about 1 / (max_weight + 1).
    max_weight: float = 24.0
    # The cap where the (dilated) motion is not zero: a moving pixel's history is
    # resampled every frame, and each resampling blurs it a little, so a long memory
    # under motion converges to a blurrier picture than a short one. 1.0, against 24:
    # game scenes at 2x +0.23 to +0.55 dB (dolly, slow_pan, fast_yaw, default); pans
    # over photographs +0.4 to +0.9 dB, and their fall from frame 8 to frame 31 halved.
    # 2.0 since the Catmull-Rom history fetch and back-projection, which blur a moving
    # history less: chosen on 6 training photographs (2 per source, 480x270, 2x) and the
    # game's scenes, against 1.0: pans +0.10 dB, zooms +0.14, cuts +0.07 over the best
    # spatial method (each photograph +0.03 to +0.21), still cameras unchanged; game
    # scenes +0.00 to +0.03, none lower, flicker no higher. 3.0 did the same.
    moving_max_weight: float = 2.0
    # The YCoCg box that bounds the history (and the current frame's reconstruction, a
    # blend of samples inside it unless ``presharpen`` is on) is the samples' 3x3 min/max
    # widened by this fraction of its own extent on each side. The history after
    # back-projection holds the detail the render pixels' boxes averaged away, and that
    # detail lies beyond the averaged samples' range (a box average has less contrast
    # than the picture under it); the exact box cut it back every frame. Proportional, so
    # a flat neighbourhood stays tight and a changed picture there is still rejected at
    # once. The output keeps its exact clamp (``_finish_output``): no halo. 0.5, chosen on
    # 6 training photographs (480x270, 2x, torch path; margin over the best spatial
    # method, against 0): still cameras +0.64 dB, pans +0.25 dB; game scenes at 2x: static
    # +0.56, moving_objects +0.49, fast_yaw and dolly +0.15, scene_cut +0.13, slow_pan and
    # default +0.05, thin_detail -0.14. 1.0 gained a little more on photographs (still
    # +0.68) but cost thin_detail 0.21 dB; 0.25 kept most of it (still +0.55).
    history_clamp_slack: float = 0.5
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
    # Unsharp amount applied to the render samples (4-neighbour cross). Off: it rang at
    # edges (a 64|191 step came out 40..215) and, clamped to stop that, cost 0.2-0.5 dB
    # on the game's scenes; the output's RCAS (below) sharpens without leaving the range.
    presharpen: float = 0.0
    # History fetch: bilinear plus a Catmull-Rom correction of each plane (_sharpen_fetch);
    # the gain scales the correction (1 = Catmull-Rom). Above 1 it makes up part of what
    # each resampling of a moving history loses: 1.3, chosen on the training photographs
    # (pans +0.66 dB, zooms +0.55 against 1.0) and the game's scenes (mean +0.01 dB, no
    # scene below -0.07); 1.5 gained more on photographs but cost thin_detail 0.19 dB.
    history_catmull_rom: bool = True
    history_sharpen_gain: float = 1.3
    # The gain at a scale that is not a whole number (1.5x, 1.7x), where the history is
    # fetched at display size pixel by pixel (``_sharpen_fetch_generic``). Before it had
    # a correction at all, a pan over photographs at 1.5x sat 1 dB under what the same
    # fetch keeps at 2x. 1.0, chosen on 6 training photographs (2 per source, 480x270,
    # 1.5x, mean of frames 8-31, against no correction): pans +1.05 dB, zooms +0.36
    # (1.3: +0.96 / +0.08); the game's scenes at 1.5x (640x360): fast_yaw, dolly and
    # scene_cut +0.24 to +0.25, slow_pan +0.16, default +0.13, moving_objects +0.02,
    # static 0, thin_detail -0.08 (1.3: -0.15).
    history_sharpen_gain_fractional: float = 1.0
    # A reset (first frame, scene cut) starts the history from EASU (FSR 1) of the frame's
    # own samples at their jittered positions, worth this much accumulated sample weight
    # in that frame's blend: the first frames after a cut are as sharp as a spatial
    # upscaler instead of the sparse jittered samples alone.
    reset_weight: float = 3.0
    # What that start leaves in the accumulated weight for the next frames: with none,
    # the second frame after a cut over soft photographs fell 1 dB below EASU+RCAS; kept
    # whole, its blur lingered (0.3 dB on the game's scenes). 0.5: -0.2 dB there, static
    # game scene -0.1 dB.
    reset_carry: float = 0.5
    # Back-projection (upscalers/temporal/back_projection.py): the fraction of each frame's
    # prediction error (its samples against the box averages of the history over their
    # footprints) added back to the history; None: off. It recovers the detail the
    # render pixels' boxes average away, where accumulation alone converges to the
    # box-blurred picture. 0.3, chosen on the training photographs and the game's scenes
    # (display 640x360, 2x, against the sharpened accumulation it replaces): photographs'
    # still cameras +1.41 dB and pans +1.56 dB; game scenes +0.16 to +0.33 dB on the five
    # with motion or cuts, moving_objects -0.05, thin_detail -0.11, static -0.29 (a
    # still camera over point-sampled edges, where RCAS had gained more). 0.5 gained 0.1-0.4
    # dB more on photographs but cost the game 0.9 dB on thin_detail; a full step (1.0)
    # followed each frame's aliasing (static -1.7, thin_detail -2.6).
    back_projection: float | None = 0.3
    # The step on moving pixels (non-zero dilated motion; None: back_projection's). Their
    # history was resampled this frame, which blurs it on top of the render pixels' box,
    # and it has at most moving_max_weight of memory; a still pixel's history is not
    # resampled, and there a larger step follows each frame's aliasing instead. 0.5,
    # chosen on the training photographs' pans and the game's moving scenes (torch path,
    # display 480x270 / 1280x720, against 0.3): pans +0.47 dB (0.6: +0.61, 0.7: +0.70);
    # game slow_pan -0.15, fast_yaw -0.08, dolly -0.07, default -0.13, thin_detail -0.52
    # (fence bars that alias, drifting: the box model's worst case); still scenes
    # unchanged.
    moving_back_projection: float | None = 0.5
    # Above this scale (display over render pixels, the larger axis) the moving step is
    # moving_back_projection times moving_step_scale / scale. The game's renders are
    # point samples, not the boxes back-projection assumes, and at 3x they are a third
    # as dense per axis: a step of 0.5 there followed their aliasing, thin_detail -0.69
    # dB and slow_pan -0.19 against 0.3, and thin_detail fell 0.5 dB below
    # docs/reports/eval_upscalers.json (issue 19 allows 0.2). 2.0 keeps 1.5x and 2x as
    # they were, where 0.5 was chosen; at 3x the step is 0.33. It costs box-filtered
    # photographs at 3x (training photographs, against 0.5: pans -0.30 dB, zooms -0.25).
    moving_step_scale: float = 2.0
    # Frames flagged FrameFlags.AREA_SAMPLES (each sample the average over its footprint:
    # a photograph or video downscaled by area) fit that box model exactly, so there the
    # back-projection's correction is preconditioned: filtered per axis by [-c, 1 + 2c, -c]
    # before it is added (back_projection.precondition). Each frame's correction has passed
    # the footprint's box twice (prediction and back), which leaves little of the detail
    # near the display's Nyquist frequency: a fixed fraction a frame recovered it too
    # slowly for 32 frames, where a least-squares solve over all frames' samples got 1-4
    # dB more (docs/reports/eval_multiframe_ls.json). At c = 0.5 the filter's gain is 2 at
    # half the Nyquist frequency, where it inverts the averaged normal operator of a
    # 2-pixel box (0.5 + 0.5 cos w), and 3 at Nyquist, where that inverse is unbounded.
    # Chosen on 6 training photographs (2 per source, 480x270, 2x, torch path, against
    # none): still cameras +0.47 dB, pans +0.37 (0.25: +0.36 / +0.32; 0.75: +0.39 / +0.12;
    # 1.0: +0.11 / -0.52). A larger step or momentum on top lost. On the game's point
    # samples it follows their aliasing (c = 0.5 at 2x: mean -0.87 dB, thin_detail -2.0),
    # so it is only for area samples. 0: off.
    area_precondition: float = 0.5
    # The same on moving pixels (non-zero dilated motion). Their history remembers two
    # frames or so (moving_max_weight), a few jitter phases, where the filter inverts the
    # operator averaged over many: a full gain follows more of each frame's aliasing.
    # Chosen on the same photographs' pans (mean of frames 8-31 against 0.5): 0.35 +0.05
    # dB (0.15 -0.10, 0.25 +0.01, 0.3 +0.04, 0.4 +0.05); their fall from frame 8 to frame
    # 31 -0.07 dB against -0.10.
    area_moving_precondition: float = 0.35
    # history_clamp_slack on area samples: 1.0 there (+0.13 dB still, +0.05 pan on the
    # training photographs with the preconditioning; 2.0 +0.16 / +0.07), where the game's
    # thin_detail keeps 0.5.
    area_history_clamp_slack: float = 1.0

    # RCAS of the output, in stops (0 strongest; None: off), as FSR 2 sharpens after
    # accumulation: the history stays unsharpened, and RCAS never leaves the range of a
    # pixel's 4 neighbours, so no halo. Off since back-projection, which sharpens from
    # the samples themselves: 2 stops on top of it changed the game's mean by 0.00 dB and
    # photographs by +0.01-0.05. (Without back-projection, 0.5 stops gained +0.04 to
    # +0.6 dB on the game's scenes.)
    # Not on a reset frame, mostly EASU's start and sharp already.
    output_sharpness: float | None = None
    # The output clamp (the 3x3 range of the frame's own colour around each display
    # pixel's render pixel) widened by this many 8-bit levels each way: issue 19 allows
    # +-4 past the local input range on a step and a checkerboard, and the detail a box
    # average hides lies just past it. 3 (one level short of the allowance), against 0:
    # game scenes at 2x (640x360, torch path) mean +0.07 dB (thin_detail -0.04); on the
    # training photographs with area_precondition, still cameras +0.57 dB, pans +0.35
    # (2 levels: +0.48 / +0.30). A flat neighbourhood comes out exact all the same: its
    # history holds no detail to let through.
    output_clamp_slack: int = 3

    def history_slack(self, area_samples: bool) -> float:
        """The history clamp's slack for frames of this kind."""
        return self.area_history_clamp_slack if area_samples else self.history_clamp_slack

    def precondition(self, area_samples: bool, moving: bool, scale: float) -> float:
        """Back-projection's preconditioning for frames of this kind (0: none), on still
        or on moving pixels, at this upscaling factor. The strengths were chosen at 2x,
        where a render pixel's box is 2 display pixels wide; at 1x the box is one pixel,
        the operator is the identity, and there is nothing to invert. On still pixels,
        whose history keeps every frame's correction, the strength goes linearly between
        the two (0.25 at 1.5x): at 1.5x the full strength ran past the samples'
        semi-convergence, and a still camera over 6 training photographs peaked at frame
        7, then lost 0.9 dB by frame 47 (mean of frames 8-31 47.55 dB); at 0.25 it is
        48.25 dB and frame 47 is within 0.11 dB of frame 8. Moving pixels remember two
        frames or so and keep their strength (at 1.5x the training pans were the same to
        0.04 dB either way; the held-out pans lost 0.12 dB with it scaled). From 2x up
        both are the full strength, as before."""
        if not area_samples:
            return 0.0
        if moving:
            return self.area_moving_precondition
        return self.area_precondition * min(max(scale - 1.0, 0.0), 1.0)

    def moving_step(self, scale: float) -> float | None:
        """Back-projection's step on moving pixels at this upscaling factor."""
        step = self.moving_back_projection
        if step is None or scale <= self.moving_step_scale:
            return step
        return step * self.moving_step_scale / scale
