"""Temporal upscaler (FSR 2 / DLSS class): jittered samples accumulated in display-size history.

Consumes exactly the frame contract of ``server/frames/frame.py`` and nothing else:

- render pixel (i, j) of this frame was sampled at (i + 0.5 + jx, j + 0.5 + jy);
- motion (mx, my), in render pixels and unjittered, takes the surface seen at a
  sample position p to p + motion in the previous frame;
- depth is NDC z in [0, 1] (1.0 sky), made linear with the camera's near/far;
- dynamic_mask marks moving objects; FrameFlags.RESET starts history afresh.

Per frame:

1. At render size (cheap): colour to YCoCg, the 3x3 YCoCg min/max box of every
   sample, motion dilated to the closest depth of the 3x3 neighbourhood (so
   edges move with the foreground, as FSR 2 does), and a per-pixel history
   trust: 0 where the reprojected position leaves the screen or was hidden in
   the previous frame (disocclusion: all previous depths around the
   reprojected position are clearly nearer than this surface), reduced on
   moving objects.
2. At display size: the current frame reconstructed at each display pixel
   from the samples at their true (jittered) positions, plus a sample weight
   that says how close the nearest real sample landed to the display pixel
   centre; history fetched at p + motion (bilinear with a Catmull-Rom correction
   of every plane, so repeated resampling under motion does not blur it); history
   and current reconstruction both clamped to the YCoCg box of the samples as
   rendered (widened by ``history_clamp_slack`` of its extent: back-projected detail
   lies beyond the box-averaged samples' range) and blended with
   ``alpha = w / (trust * W + w)`` where W is the accumulated weight (capped, so
   alpha never drops below about 1 / W_max; the cap is far lower on moving pixels,
   whose history every resampling blurs).
   After a reset the history starts as FSR 1's EASU of the frame's own samples,
   its taps at their jittered positions, worth ``reset_weight`` in that frame's
   blend and ``reset_carry`` after it: the frames after a cut are about as good as
   a spatial upscaler's.
3. Back-projection (``back_projection.py``): the new history predicts this frame's
   samples (the box over each sample's footprint at its jittered position) and a
   fraction of the error goes back to the display pixels each footprint covers.
   Accumulation alone converges to the picture blurred by the render pixel's box;
   these steps recover what the overlapping, shifted boxes still tell apart. The
   fraction is larger on moving pixels, whose history this frame's resampling
   blurred (``moving_back_projection``). Not on a reset frame, which is mostly EASU's
   start. On frames flagged AREA_SAMPLES (true box averages, as photographs and video
   downscaled by area) the correction is preconditioned (``area_precondition``).
4. Output: uint8 sRGB (3, H, W), what ring U holds; conversion from YCoCg, scale,
   rounding and clamp are one matrix product and a clamp. RCAS can sharpen it
   (``output_sharpness``; off by default since back-projection) and each display
   pixel is clamped to the 3x3 range of the frame's colour around its render pixel,
   widened by ``output_clamp_slack`` levels: detail without a halo past the input's
   local range. Not on a reset frame.

Colour space: history is kept in YCoCg of the *sRGB-encoded* values. The
input and the output are sRGB, so no transfer-function work happens at display
size (a pow per sub-pixel costs as much as the rest of the blend on a CPU), and
the neighbourhood box is perceptually even, so the clamp does not let dark
ghosts through while clipping bright ones. Averaging encoded values instead of
linear light differs only where samples of very different brightness are
mixed inside one display pixel; the clamp bounds that error to the local box.
YCoCg is linear in RGB, so interpolation and blending commute with it and the
one conversion back happens at the output.

Display-size work is counted in passes over the image (each about 0.6 ms at
1280x720 on 2 cores), so scratch buffers are kept between frames and the
sub-pixel planes of an integer scale go to grid_sample as a batch (its CPU
kernel parallelizes over the batch only).

NaN and Inf never enter the history: inputs are sanitized and the fetched
history is cleaned before use (a planted NaN is dropped, not spread).

On the CPU with float32 history the same steps run as compiled loops
(``temporal_cpu.py``, numba): eager torch pays a pass over memory per operation,
which the loops fuse into three passes at render size and one at display size.
The torch code below stays the reference and the CUDA path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import torch
import torch.nn.functional as F

from server.frames.frame import FrameFlags, RenderFrame, Size
from upscalers.base import BACKENDS, Backend, Upscaler, numba_can_run
from upscalers.fsr1.easu import Easu
from upscalers.fsr1.rcas import Rcas
from upscalers.kernels.readiness import kernels_ready
from upscalers.temporal import ops
from upscalers.temporal.back_projection import AxisTaps, back_project, cached_axis_taps
from upscalers.temporal.params import TemporalParams

if TYPE_CHECKING:
    from upscalers.temporal.cpu import HostTemporal


@dataclass
class _DisplayInputs:
    """Per-frame inputs of the display-size blend in layout D = (S, S, h, w): planar for
    an integer scale S (display pixel (i S + a, j S + b) at [a, b, i, j], so render-size
    values broadcast as (C, 1, 1, h, w) views with long contiguous rows), else S = 1 and
    (h, w) = (H, W) with render-size values upsampled."""

    cur: torch.Tensor  # (3, *D) current-frame reconstruction, YCoCg
    lo: torch.Tensor  # (3, *D) broadcastable: YCoCg box
    hi: torch.Tensor
    prev_weight: torch.Tensor  # (1, *D) broadcastable: trusted accumulated weight
    weight: torch.Tensor  # (1, *D) broadcastable: this frame's sample weight
    motion: torch.Tensor  # (*D, 2) broadcastable: motion in render pixels


class TemporalUpscaler(Upscaler):
    """Jittered-sample accumulation with reprojection, disocclusion and a YCoCg clamp."""

    name: ClassVar[str] = "temporal"
    temporal: ClassVar[bool] = True

    def __init__(
        self,
        params: TemporalParams | None = None,
        *,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        backend: Backend = "auto",
    ) -> None:
        """``backend``: "numba" runs the compiled CPU loops (CPU and float32 history only),
        "torch" the tensor code, "auto" the loops wherever they can run."""
        self.params = params or TemporalParams()

        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        if backend not in BACKENDS:
            raise ValueError(
                f"unknown temporal backend {backend!r}; allowed: {', '.join(BACKENDS)}"
            )
        if backend == "numba" and not numba_can_run(self.device, dtype):
            raise ValueError(
                "temporal backend 'numba' runs on the CPU with float32 history, "
                f"got device {self.device} and dtype {dtype}; use backend 'torch' or 'auto'"
            )
        self.backend: Backend = backend
        # ``dtype`` is how the history is stored (float16 halves its memory traffic on a
        # GPU); the arithmetic is float32 whatever it is. float16 positions are off by up
        # to 0.6 px at 1280 px (10 bits of mantissa), and a history fetched there and
        # blended back every frame drifts: measured, up to 0.2 of full scale after six
        # frames of motion. float32 arithmetic with float16 storage stays within a few
        # 8-bit steps (tests/test_temporal.py).
        self.storage_dtype = dtype
        self.dtype = torch.float32
        # Display-size YCoCg history (1, 3, H, W) and, at render size, the accumulated
        # sample weight (h, w) and the 2x2 max of linear depth, both of the last frame.
        self._history: torch.Tensor | None = None
        self._weight: torch.Tensor | None = None
        self._prev_far: torch.Tensor | None = None
        self._prev_jitter = (0.0, 0.0)
        self._key: tuple[Size, Size, torch.device, torch.dtype] | None = None
        self._base_grid: torch.Tensor | None = None
        # Display-size scratch kept between frames (a fresh large buffer costs page faults).
        self._grid_buffer: torch.Tensor | None = None
        self._neighbour_bufs: tuple[torch.Tensor, torch.Tensor] | None = None
        # The numba path's state and buffers for the current geometry (None: torch path).
        self._host: HostTemporal | None = None
        self._rcas: Rcas | None = None  # the output's sharpening (torch path)
        self._easu: Easu | None = None  # a reset's spatial start (torch path)

    def reset(self) -> None:
        self._history = None
        self._weight = None
        self._prev_far = None
        self._prev_jitter = (0.0, 0.0)
        if self._host is not None:
            self._host.reset()

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        p = self.params
        dev = ops.input_device(frame, self.device)
        dt = self.dtype
        display = Size(int(display_size[0]), int(display_size[1]))
        h, w = frame.depth.shape[:2]
        render = Size(w, h)
        key = (render, display, dev, self.storage_dtype)
        if key != self._key:
            self.reset()
            self._key = key
            self._base_grid = None
            self._grid_buffer = None
            self._neighbour_bufs = None
            self._host = self._host_for(render, display, dev)
        if frame.meta.flags & FrameFlags.RESET:
            self.reset()
        big_w, big_h = display
        jit = ops.jitter(frame)
        if self._host is not None:
            return self._upscale_host(self._host, frame, jit)

        # ---- render size: colour, box, dilated motion, trust, accumulated weight ----
        raw, ycocg, lo, hi, prev_weight, mv = self._render_stage(frame, jit, ops.near_far(frame))
        self._prev_jitter = jit

        # ---- display size ----
        scale = _integer_scale(render, display) or 1
        if scale > 1:
            inputs = self._blocked_inputs(ycocg, lo, hi, prev_weight, mv, jit, scale)
        else:
            inputs = self._generic_inputs(ycocg, lo, hi, prev_weight, mv, jit, display)
        # The sharpened reconstruction stays inside the samples' (widened) range; the
        # output's exact clamp keeps a 64|191 step from coming out 40..215.
        inputs.cur.clamp_(inputs.lo, inputs.hi)
        layout = inputs.cur.shape[1:]
        if self._base_grid is None:
            self._base_grid = ops.pixel_grid(display, scale, dev, dt)
        history = self._history
        reset = history is None
        if history is None:
            # A reset: the history starts as the frame's own spatial reconstruction.
            color = ops.as_tensor(frame.color, dev)
            spatial = ops.spatial_reconstruction(color, display, jit, self._reset_easu())
            if scale > 1:
                prev = ops.to_planar(spatial, scale)
            else:
                prev = spatial.view(3, 1, 1, big_h, big_w)
        elif bool(mv.abs().max() == 0.0):
            # Nothing moved: the fetch would be the identity.
            prev = torch.nan_to_num(ops.to_planar(history[0], scale).to(dt), nan=0.0)
        else:
            prev = self._fetch_history(history, inputs.motion, layout, w, h)
            # Non-finite history (never written by this code) is dropped before the
            # Catmull-Rom correction can spread it; the clamp then moves it into the box.
            torch.nan_to_num_(prev, nan=0.0, posinf=0.0, neginf=0.0)
            if p.history_catmull_rom and scale > 1:
                for plane in prev:
                    self._sharpen_fetch(plane, mv, scale)
            elif p.history_catmull_rom:
                self._sharpen_fetch_generic(prev, inputs.motion, render, display)
        prev.clamp_(inputs.lo, inputs.hi)
        denom = inputs.prev_weight + inputs.weight
        alpha = torch.div(inputs.weight, denom, out=denom)
        new = prev.lerp_(inputs.cur, alpha)
        if scale > 1:
            if history is None:
                history = torch.empty((1, 3, big_h, big_w), device=dev, dtype=self.storage_dtype)
            ops.to_planar(history[0], scale).copy_(new)
        else:
            history = new.reshape(1, 3, big_h, big_w).to(self.storage_dtype)
        self._history = history
        step = p.back_projection
        if step is not None and not reset:
            work = history[0] if history.dtype == torch.float32 else history[0].float()
            taps = self._back_taps(render, display, jit)
            area = bool(frame.meta.flags & FrameFlags.AREA_SAMPLES)
            factor = ops.axis_scale(render, display)
            steps = self._moving_map(step, p.moving_step(factor), mv, display)
            still_c, moving_c = (
                p.precondition(area, False, factor),
                p.precondition(area, True, factor),
            )
            pre = self._moving_map(still_c, moving_c, mv, display)
            back_project(work, raw, *taps, steps, pre)
            if work.data_ptr() != history.data_ptr():
                history[0].copy_(work)
        rgb8 = ops.ycocg_to_rgb8(history[0])
        # A reset frame is mostly EASU's start, sharp already: RCAS on top lost 0.3 dB
        # there on photographs, and it stays as it is.
        return rgb8 if reset else self._finish_output(rgb8, frame)

    def _moving_map(
        self, still: float, moving_value: float | None, mv: torch.Tensor, display: Size
    ) -> float | torch.Tensor:
        """A back-projection setting (its step, its preconditioning): ``still`` everywhere,
        or an (H, W) map with ``moving_value`` on display pixels whose render pixel
        (nearest) has non-zero dilated motion ``mv`` (2, h, w)."""
        _, h, w = mv.shape
        if moving_value is None or moving_value == still or not bool(mv.any()):
            return still
        moving = (mv[0] != 0.0) | (mv[1] != 0.0)
        steps = torch.where(moving, moving_value, still).to(torch.float32)
        iy = ops.nearest_index(display.height, h, mv.device)
        ix = ops.nearest_index(display.width, w, mv.device)
        return steps.index_select(0, iy).index_select(1, ix)

    def _back_taps(
        self, render: Size, display: Size, jit: tuple[float, float]
    ) -> tuple[AxisTaps, AxisTaps]:
        return (
            cached_axis_taps(render.width, display.width, jit[0]),
            cached_axis_taps(render.height, display.height, jit[1]),
        )

    def _reset_easu(self) -> Easu:
        if self._easu is None:
            self._easu = Easu(dtype=torch.float32)
        return self._easu

    def _finish_output(self, rgb8: torch.Tensor, frame: RenderFrame) -> torch.Tensor:
        """RCAS of the (3, H, W) uint8 output if asked (``TemporalParams.output_sharpness``),
        quantized as the numba path's ``rcas_to_rgb8`` does (clamp, x 255 + 0.5, floor),
        then, after RCAS or back-projection, clamped to the 3x3 range of the frame's own
        colour around each display pixel's render pixel: RCAS keeps a pixel near its
        neighbours' range, not inside it (a 64|191 step came out 57..198), and
        back-projection, which undoes a blur, overshoots an edge the samples cannot
        resolve."""
        stops = self.params.output_sharpness
        if stops is None and self.params.back_projection is None:
            return rgb8
        _, big_h, big_w = rgb8.shape
        dev = rgb8.device
        if stops is None:
            out = rgb8.to(torch.float32)
        else:
            if self._rcas is None:
                self._rcas = Rcas(sharpness=stops)
            padded = torch.empty((3, big_h + 2, big_w + 2), device=dev, dtype=torch.float32)
            padded[:, 1:-1, 1:-1].copy_(rgb8).mul_(1.0 / 255.0)
            sharp = self._rcas(padded)
            out = sharp.mul_(255.0).add_(0.5).floor_().clamp_(0.0, 255.0)
        color = ops.as_tensor(frame.color, dev).permute(2, 0, 1).to(torch.float32)
        lo, hi = ops.render_range_at_display(color, big_h, big_w, self.params.output_clamp_slack)
        return torch.minimum(torch.maximum(out, lo), hi).to(torch.uint8)

    def _host_for(self, render: Size, display: Size, dev: torch.device) -> HostTemporal | None:
        """The numba path's state for a new geometry, or None where the torch path runs."""
        if self.backend == "torch":
            return None
        if not numba_can_run(dev, self.storage_dtype):
            if self.backend == "numba":
                raise ValueError(f"temporal backend 'numba' runs on the CPU, got a frame on {dev}")
            return None
        # Imported here: numba takes a while to import, and only this path needs it.
        from upscalers.temporal import cpu as temporal_cpu

        if self.backend == "auto" and not (
            temporal_cpu.supports(render, display) and kernels_ready("temporal")
        ):
            return None
        scale = _integer_scale(render, display) or 1
        return temporal_cpu.HostTemporal(self.params, render, display, scale)

    def _upscale_host(
        self, host: HostTemporal, frame: RenderFrame, jit: tuple[float, float]
    ) -> torch.Tensor:
        out = host.upscale(frame, jit, ops.near_far(frame))
        # Views of the host's state: inspectable (and writable) as the torch path's.
        history, weight = host.history, host.weight
        assert history is not None and weight is not None
        self._history = torch.from_numpy(history).unsqueeze(0)
        self._weight = torch.from_numpy(weight)
        return out

    def _render_stage(
        self, frame: RenderFrame, jit: tuple[float, float], nf: tuple[float, float] | None
    ) -> tuple[torch.Tensor, ...]:
        """YCoCg samples as rendered and presharpened if asked, the 3x3 box of the samples
        as rendered, the trusted accumulated weight and the dilated motion; keeps this
        frame's 2x2 max depth for the next one."""
        p = self.params
        dev = ops.input_device(frame, self.device)
        dt = self.dtype
        h, w = frame.depth.shape[:2]
        ycocg = ops.rgb8_to_ycocg(ops.as_tensor(frame.color, dev), dt)
        # The box of the samples as rendered, before the presharpening, widened by
        # history_clamp_slack (area_history_clamp_slack on area samples): it bounds the
        # history and the sharpened current frame alike.
        raw = ycocg
        area = bool(frame.meta.flags & FrameFlags.AREA_SAMPLES)
        lo, hi = ops.widen_box(*ops.box_3x3(raw), p.history_slack(area))
        if p.presharpen > 0.0:
            ycocg = ops.sharpen(raw, p.presharpen)
        depth = ops.as_tensor(frame.depth, dev).to(dt)
        depth = torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)
        motion = ops.as_tensor(frame.motion, dev).to(dt)
        lim = 4.0 * max(w, h)
        motion = torch.nan_to_num(motion, nan=0.0, posinf=0.0, neginf=0.0).clamp_(-lim, lim)
        if nf is None:
            lin = depth
        else:
            near, far = nf
            lin = torch.reciprocal(depth.mul(-(far - near) / (near * far)).add_(1.0 / near))
        mask = ops.as_tensor(frame.dynamic_mask, dev)
        # Most frames have no moving object: no need to dilate an empty mask.
        mask_d = ops.box_3x3(mask.to(dt).unsqueeze(0))[1][0] if bool(mask.any()) else None
        lin_d, mv = ops.closest_3x3(lin, motion.permute(2, 0, 1))
        prev_weight = self._reproject_weight(lin_d, mv, mask_d, jit)
        self._prev_far = ops.max_2x2(lin)
        return raw, ycocg, lo, hi, prev_weight, mv

    def _fetch_history(
        self, history: torch.Tensor, motion: torch.Tensor, layout: torch.Size, w: int, h: int
    ) -> torch.Tensor:
        """Bilinear fetch of the (1, 3, H, W) history at p + motion, in the blend layout
        (3, *layout). The sub-pixel planes of an integer scale go in as a batch: the CPU
        grid_sample kernel splits its work over the batch, not within one image."""
        assert self._base_grid is not None
        dev, dt = history.device, self.dtype
        history = history.to(dt)  # float32 positions need a float32 image to sample
        step = torch.tensor([2.0 / w, 2.0 / h], device=dev, dtype=dt)
        grid = self._grid_buffer
        if grid is None or grid.shape != self._base_grid.shape:
            grid = self._grid_buffer = torch.empty_like(self._base_grid)
        base = self._base_grid
        if base.shape[0] > 1:
            # Sub-pixel (a, b) of a block sits at a constant offset from sub-pixel (0, 0):
            # the motion is added at render size and the offsets in the one display pass.
            offsets = base[:, :, :1, :1] - base[:1, :1, :1, :1]
            torch.add(torch.addcmul(base[:1, :1], motion, step), offsets, out=grid)
        else:
            torch.addcmul(base, motion, step, out=grid)
        s_a, s_b, rows, cols = layout
        n = s_a * s_b
        fetched = F.grid_sample(
            history.expand(n, -1, -1, -1),
            grid.view(n, rows, cols, 2),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )
        return fetched.view(s_a, s_b, 3, rows, cols).permute(2, 0, 1, 3, 4)

    def _sharpen_fetch(self, luma: torch.Tensor, mv: torch.Tensor, scale: int) -> None:
        """Turn the bilinear history fetch of one plane (S, S, h, w) into a Catmull-Rom
        one, as FSR 2 fetches history: per axis, Catmull-Rom at fraction t equals bilinear
        minus t (1 - t) / 2 times the second difference of the bilinear result, exactly
        where the motion is locally uniform (the cross term is dropped). Repeated bilinear
        resampling otherwise blurs the history a little more every frame under motion.
        Called on each plane: with luma alone, photographs panned by a fraction of a
        pixel a frame lost up to 1.5 dB of colour detail by frame 31."""
        frac = mv.mul(float(scale))
        frac.sub_(frac.floor())
        # c = -gain * t (1 - t) / 2 per axis; the result is luma (1 - 2 cx - 2 cy)
        # + cx * (left + right) + cy * (up + down).
        c = frac.mul(frac.neg().add_(1.0)).mul_(-0.5 * self.params.history_sharpen_gain)
        centre = c.sum(0).mul_(-2.0).add_(1.0)
        nx, ny = self._neighbour_buffers(luma.shape)
        ops.neighbour_sum_planar(luma, 1, nx)
        ops.neighbour_sum_planar(luma, 0, ny)
        luma.mul_(centre)
        luma.addcmul_(nx, c[0])
        luma.addcmul_(ny, c[1])

    def _sharpen_fetch_generic(
        self, prev: torch.Tensor, motion: torch.Tensor, render: Size, display: Size
    ) -> None:
        """``_sharpen_fetch`` for any other scale: ``prev`` (3, 1, 1, H, W) fetched at
        display size, ``motion`` (1, 1, H, W, 2) the render motion of each display pixel;
        its fraction in display pixels is the motion times display over render size per
        axis (1.5 at 1.5x); the gain is ``history_sharpen_gain_fractional``."""
        scales = torch.tensor(
            [display.width / render.width, display.height / render.height],
            device=prev.device,
            dtype=self.dtype,
        )
        frac = motion[0, 0].mul(scales).permute(2, 0, 1)
        frac.sub_(frac.floor())
        gain = self.params.history_sharpen_gain_fractional
        c = frac.mul(frac.neg().add_(1.0)).mul_(-0.5 * gain)
        centre = c.sum(0).mul_(-2.0).add_(1.0)
        for plane in prev[:, 0, 0]:
            padded = F.pad(plane[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
            nx = padded[1:-1, :-2] + padded[1:-1, 2:]
            ny = padded[:-2, 1:-1] + padded[2:, 1:-1]
            plane.mul_(centre)
            plane.addcmul_(nx, c[0])
            plane.addcmul_(ny, c[1])

    def _neighbour_buffers(self, shape: torch.Size) -> tuple[torch.Tensor, torch.Tensor]:
        bufs = self._neighbour_bufs
        if bufs is None or bufs[0].shape != shape:
            assert self._history is not None
            h = self._history
            bufs = self._neighbour_bufs = (
                torch.empty(shape, device=h.device, dtype=self.dtype),
                torch.empty(shape, device=h.device, dtype=self.dtype),
            )
        return bufs

    # -- render size -----------------------------------------------------------------

    def _reproject_weight(
        self,
        lin_d: torch.Tensor,
        mv: torch.Tensor,
        mask_d: torch.Tensor | None,
        jit: tuple[float, float],
    ) -> torch.Tensor:
        """(h, w) accumulated weight fetched at the reprojected position, times trust:
        0 off screen or where disoccluded, reduced on moving objects; after a reset, the
        weight the spatial reconstruction starts the history with."""
        p = self.params
        h, w = lin_d.shape
        dev, dt = lin_d.device, lin_d.dtype
        if self._prev_far is None or self._weight is None:
            return torch.full((h, w), p.reset_weight, device=dev, dtype=dt)
        xs = torch.arange(w, device=dev, dtype=dt).add_(0.5 + jit[0])
        ys = torch.arange(h, device=dev, dtype=dt).add_(0.5 + jit[1])
        qx = mv[0] + xs
        qy = mv[1] + ys.unsqueeze(1)
        inside = (qx >= 0.0) & (qx <= w) & (qy >= 0.0) & (qy <= h)
        pjx, pjy = self._prev_jitter
        kx = (qx - (0.5 + pjx)).floor_().clamp_(0, w - 1).long()
        ky = (qy - (0.5 + pjy)).floor_().clamp_(0, h - 1).long()
        idx = ky.mul_(w).add_(kx)
        # Visible last frame if the farthest depth around the reprojected position is not
        # clearly nearer than this surface.
        far = self._prev_far.view(-1).take(idx).mul_(1.0 + p.depth_tolerance)
        trust = (inside & (far >= lin_d)).to(dt)
        if mask_d is not None:
            trust.mul_(mask_d.mul(p.dynamic_keep - 1.0).add_(1.0))
        weight = torch.nan_to_num(self._weight.view(-1).take(idx), nan=0.0, posinf=0.0)
        # Moving pixels keep less: every frame resamples their history (see
        # TemporalParams.moving_max_weight).
        moving = ((mv[0] != 0.0) | (mv[1] != 0.0)).to(dt)
        cap = moving.mul_(p.moving_max_weight - p.max_weight).add_(p.max_weight)
        return torch.minimum(weight.clamp_(min=0.0), cap).mul_(trust)

    def _store_weight(self, prev_weight: torch.Tensor, mean_sample_weight: float) -> None:
        if self._history is None:
            # The reset's spatial start leaves only reset_carry to later frames: kept
            # whole in the weight, its blur would linger (0.3 dB on the game's scenes).
            mean_sample_weight += self.params.reset_carry - self.params.reset_weight
        self._weight = (prev_weight + mean_sample_weight).clamp_(max=self.params.max_weight)

    # -- display layouts -------------------------------------------------------------

    def _axis_weights(
        self, n: int, display: int, render: int, j: float, dev: torch.device
    ) -> torch.Tensor:
        p = self.params
        g = ops.axis_weight(n, display, render, j, p.sample_sigma, dev, self.dtype)
        return g.clamp_(min=p.min_sample_weight)

    def _blocked_inputs(
        self,
        ycocg: torch.Tensor,
        lo: torch.Tensor,
        hi: torch.Tensor,
        prev_weight: torch.Tensor,
        mv: torch.Tensor,
        jit: tuple[float, float],
        scale: int,
    ) -> _DisplayInputs:
        _, h, w = ycocg.shape
        dev = ycocg.device
        cur = torch.empty((3, scale, scale, h, w), device=dev, dtype=self.dtype)
        ops.reconstruct_blocked(ycocg, scale, jit, self.params.reconstruct_sharpness, cur)
        gx = self._axis_weights(scale, w * scale, w, jit[0], dev)
        gy = self._axis_weights(scale, h * scale, h, jit[1], dev)
        weight = torch.outer(gy, gx)
        self._store_weight(prev_weight, float(weight.mean()))
        return _DisplayInputs(
            cur=cur,
            lo=lo.view(3, 1, 1, h, w),
            hi=hi.view(3, 1, 1, h, w),
            prev_weight=prev_weight.view(1, 1, 1, h, w),
            weight=weight.view(1, scale, scale, 1, 1),
            motion=mv.permute(1, 2, 0).contiguous().view(1, 1, h, w, 2),
        )

    def _generic_inputs(
        self,
        ycocg: torch.Tensor,
        lo: torch.Tensor,
        hi: torch.Tensor,
        prev_weight: torch.Tensor,
        mv: torch.Tensor,
        jit: tuple[float, float],
        display: Size,
    ) -> _DisplayInputs:
        _, h, w = ycocg.shape
        big_w, big_h = display
        dev, dt = ycocg.device, self.dtype
        k = self.params.reconstruct_sharpness
        grid = ops.jittered_grid(display, Size(w, h), jit, k, dev, dt)
        cur = F.grid_sample(
            ycocg.unsqueeze(0), grid, mode="bilinear", padding_mode="border", align_corners=False
        )[0]
        # Nearest render pixel of each display pixel (unjittered: the box is 3x3 wide).
        iy = ops.nearest_index(big_h, h, dev)
        ix = ops.nearest_index(big_w, w, dev)
        packed = torch.cat((lo, hi, prev_weight.unsqueeze(0), mv))
        up = packed.index_select(1, iy).index_select(2, ix).view(9, 1, 1, big_h, big_w)
        gx = self._axis_weights(big_w, big_w, w, jit[0], dev)
        gy = self._axis_weights(big_h, big_h, h, jit[1], dev)
        self._store_weight(prev_weight, float(gx.mean() * gy.mean()))
        return _DisplayInputs(
            cur=cur.view(3, 1, 1, big_h, big_w),
            lo=up[0:3],
            hi=up[3:6],
            prev_weight=up[6:7],
            weight=torch.outer(gy, gx).view(1, 1, 1, big_h, big_w),
            motion=up[7:9].permute(1, 2, 3, 4, 0),
        )


def _integer_scale(render: Size, display: Size) -> int | None:
    s = display.width // render.width
    if s >= 1 and display.width == s * render.width and display.height == s * render.height:
        return s
    return None
