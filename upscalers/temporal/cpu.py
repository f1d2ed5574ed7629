"""The numba backend of the temporal upscaler: host buffers around ``temporal_cpu_kernels``.

Same algorithm, parameters and outputs as the torch path of ``temporal.py`` (which
stays the reference and the CUDA path); see ``temporal_cpu_kernels`` for why it is
faster on the CPU. One ``HostTemporal`` serves one geometry (render size, display
size): it keeps the state between frames (display-size YCoCg history, render-size
accumulated weight and 2x2 max depth, last jitter) and the scratch buffers, so a
frame allocates nothing of display size (its output array is reused too, once the
caller has let the last result go). Three kernels run at render size and one at
display size per frame.

The per-jitter tables (reconstruction taps, sample weights, jittered grids) and the
fetch grid are made by the torch path's own helpers, on a row or a column, so they
are the same numbers; the jitter sequence repeats, so its tables are cached.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import torch

from server.frames.frame import FrameFlags, RenderFrame, Size
from upscalers.fsr1 import cpu_kernels as fsr1_kernels
from upscalers.fsr1.easu import Easu
from upscalers.temporal import cpu_kernels as kernels
from upscalers.temporal import ops
from upscalers.temporal.back_projection import (
    AxisTaps,
    Regular2x,
    cached_axis_taps,
    cached_regular_2x,
)

if TYPE_CHECKING:
    from upscalers.temporal.params import TemporalParams

F32Array = npt.NDArray[np.float32]
I64Array = npt.NDArray[np.int64]
_CPU = torch.device("cpu")
_MAX_CACHED_PHASES = 128  # more than the longest jitter sequence (72 phases at 3x)
_MAX_KEPT_OUTPUTS = 2
_NO_TAPS = np.zeros(0, np.float32)  # bp_predict_x without a pattern


@dataclass(frozen=True)
class _BlockedPhase:
    """Tables of one jitter for an integer scale S (see ``kernels.display_blocked``)."""

    tap_y: I64Array  # (S,) row offset of the upper sample of sub-pixel row a
    frac_y: F32Array  # (S,) and the fraction towards the next row
    tap_x: I64Array
    frac_x: F32Array
    sub_weight: F32Array  # (S, S) sample weight of sub-pixel (a, b)
    mean_weight: np.float32  # what the accumulated weight gains this frame


@dataclass(frozen=True)
class _GenericPhase:
    """Tables of one jitter for any other scale (see ``kernels.display_generic``)."""

    grid_x: F32Array  # (W,) normalized render x sampled by display column X
    grid_y: F32Array  # (H,)
    weight_x: F32Array  # (W,) sample weight factor of display column X
    weight_y: F32Array
    mean_weight: np.float32


_Phase = _BlockedPhase | _GenericPhase


@dataclass
class _RenderBuffers:
    """Render-size working buffers of one frame, planes first; "padded": one replicated
    column on each side (column x at x + 1)."""

    raw: F32Array  # (3, h, w + 2) padded YCoCg of the colour
    ycc: F32Array  # (3, h, w + 2) padded, presharpened
    lin: F32Array  # (h, w + 2) padded linear depth
    motion: F32Array  # (2, h, w + 2) padded sanitized motion
    mask: F32Array  # (h, w + 2) padded dynamic mask
    lo: F32Array  # (3, h, w) 3x3 box
    hi: F32Array
    dilated: F32Array  # (2, h, w) motion of the closest depth around
    prev_weight: F32Array  # (h, w) trusted accumulated weight

    @staticmethod
    def allocate(w: int, h: int) -> _RenderBuffers:
        def planes(n: int, width: int) -> F32Array:
            return np.empty((n, h, width), np.float32)

        return _RenderBuffers(
            planes(3, w + 2), planes(3, w + 2), planes(1, w + 2)[0], planes(2, w + 2),
            planes(1, w + 2)[0], planes(3, w), planes(3, w), planes(2, w), planes(1, w)[0],
        )  # fmt: skip


def supports(render: Size, display: Size) -> bool:
    """Whether the kernels take this geometry: their gather offsets are float32 integers,
    exact below 2^24 pixels (beyond 5120x3240)."""
    limit = kernels.MAX_PIXELS
    return render.width * render.height < limit and display.width * display.height < limit


@lru_cache(maxsize=512)
def _kernel_x_tables(
    n_render: int, n_display: int, jitter: float
) -> tuple[I64Array, F32Array, I64Array, F32Array]:
    """The x tables of ``cached_axis_taps`` as the kernels take them, (taps, n) and
    contiguous (forward index, weight, back index, weight): transposed once per size and
    jitter, as the tables are built, not every frame."""
    t = cached_axis_taps(n_render, n_display, jitter)
    return (
        np.ascontiguousarray(t.forward_index.T),
        np.ascontiguousarray(t.forward_weight.T),
        np.ascontiguousarray(t.back_index.T),
        np.ascontiguousarray(t.back_weight.T),
    )


def _f32(values: torch.Tensor) -> F32Array:
    return np.ascontiguousarray(values.numpy(), dtype=np.float32)


class HostTemporal:
    """``TemporalUpscaler``'s per-frame work for one geometry on the CPU with numba kernels."""

    def __init__(self, params: TemporalParams, render: Size, display: Size, scale: int) -> None:
        """``scale``: the integer scale display / render, or 1 for any other ratio (the
        generic path, as in the torch path)."""
        if not supports(render, display):
            raise ValueError(f"temporal numba path: {render} -> {display} is too large")
        self.params = params
        self.render = render
        self.display = display
        self.scale = scale
        # Back-projection's step on moving pixels: fixed by the geometry.
        self._factor = ops.axis_scale(render, display)  # the upscaling factor
        self._moving_step = params.moving_step(self._factor)
        w, h = render
        big_w, big_h = display
        self._buf = _RenderBuffers.allocate(w, h)
        # History of the last frame and the buffer the next one is written into (the fetch
        # reads around each pixel, so the history cannot be written in place).
        self._history = np.zeros((3, big_h, big_w), np.float32)
        self._spare = np.zeros((3, big_h, big_w), np.float32)
        self._rcas_in = np.zeros((3, big_h + 2, big_w + 2), np.float32)  # output, bordered
        # Back-projection's scratch: the prediction along the columns, the error.
        self._across = np.zeros((3, big_h, w), np.float32)
        self._error = np.zeros((3, h, w), np.float32)
        self._box_lo = np.zeros((h, w, 3), np.uint8)  # the colour's 3x3 box (render size)
        self._box_hi = np.zeros((h, w, 3), np.uint8)
        self._weight = np.zeros((h, w), np.float32)
        self._prev_far = np.zeros((h, w), np.float32)
        self._has_history = False
        self._prev_jitter = (0.0, 0.0)
        self._phases: dict[tuple[float, float], _Phase] = {}
        self._easu = Easu(dtype=torch.float32)  # a reset's spatial start
        self._outputs: list[npt.NDArray[np.uint8]] = []
        self._to_ycocg = _f32(torch.tensor(ops._RGB_TO_YCOCG).mul_(1.0 / 255.0))
        self._step = (np.float32(2.0 / w), np.float32(2.0 / h))  # as _fetch_history's ``step``
        # Display pixel centres as grid_sample coordinates (``ops.pixel_grid``), per axis.
        self._grid_x = _f32(ops.pixel_grid(Size(big_w, 1), 1, _CPU, torch.float32)[0, 0, 0, :, 0])
        self._grid_y = _f32(ops.pixel_grid(Size(1, big_h), 1, _CPU, torch.float32)[0, 0, :, 0, 1])
        # An integer scale's fetch grid (``_fetch_history``): per display column X, the x of
        # sub-pixel (0, 0) of its block and X's offset from it, as the torch path forms
        # them; per sub-pixel row a, the offset in y.
        s = max(scale, 1)
        sub_x = np.arange(big_w) % s
        self._grid_x_base = np.ascontiguousarray(self._grid_x[np.arange(big_w) - sub_x])
        self._grid_x_off = np.ascontiguousarray((self._grid_x[:s] - self._grid_x[0])[sub_x])
        self._grid_y_off = self._grid_y[:s] - self._grid_y[0]
        # Any other scale: the render pixel whose box, weight and motion each display pixel takes.
        self._near_x = ops.nearest_index(big_w, w, _CPU).numpy()
        self._near_y = ops.nearest_index(big_h, h, _CPU).numpy()
        # and the motion's scale to display pixels per axis, as ``_sharpen_fetch_generic``.
        self._display_per_render = (np.float32(big_w / w), np.float32(big_h / h))
        self._steps = np.empty((h, w), np.float32)  # back-projection's step per render pixel
        self._preconditions = np.empty((h, w), np.float32)  # and its preconditioning
        # The whole correction, for area samples' preconditioning (made at first need).
        self._correction: F32Array | None = None

    def reset(self) -> None:
        """Forget the history (the buffers are kept)."""
        self._has_history = False
        self._prev_jitter = (0.0, 0.0)

    @property
    def history(self) -> F32Array | None:
        """(3, H, W) YCoCg history of the last frame (None after a reset); writable."""
        return self._history if self._has_history else None

    @property
    def weight(self) -> F32Array | None:
        """(h, w) accumulated sample weight of the last frame (None after a reset); writable."""
        return self._weight if self._has_history else None

    def upscale(
        self, frame: RenderFrame, jit: tuple[float, float], nf: tuple[float, float] | None
    ) -> torch.Tensor:
        """One frame, with the jitter and camera range as the torch path sanitized them
        (``ops.jitter``, ``ops.near_far``): (3, H, W) uint8 sRGB, a view of an (H, W, 3)
        array (the ring U layout) that no result the caller still holds shares."""
        phase = self._phase(jit)
        stored = phase.mean_weight
        if not self._has_history:
            p = self.params  # as _store_weight
            stored = np.float32(stored + (p.reset_carry - p.reset_weight))
        moving = self._render_stage(frame, jit, nf, stored)
        reset = not self._has_history
        if reset:
            # A reset: the history starts as the frame's own spatial reconstruction (the
            # torch path's helper; one frame in many, so its speed matters little).
            rgb8 = ops.as_tensor(frame.color, _CPU)
            spatial = ops.spatial_reconstruction(rgb8, self.display, jit, self._easu)
            np.copyto(self._history, spatial.numpy())
            mode = kernels.PREV_IN_PLACE
        elif moving == 0:
            mode = kernels.PREV_IN_PLACE  # nothing moved: the fetch would be the identity
        else:
            mode = kernels.PREV_FETCH
        out = self._output()
        self._display_stage(phase, mode, out)
        if not reset:  # as TemporalUpscaler.upscale
            self._finish_output(frame, jit, moving > 0, out)
        self._history, self._spare = self._spare, self._history
        self._has_history = True
        return torch.from_numpy(out).permute(2, 0, 1)

    def _finish_output(
        self,
        frame: RenderFrame,
        jit: tuple[float, float],
        any_moving: bool,
        out: npt.NDArray[np.uint8],
    ) -> None:
        """Back-projection of the new history (in the spare buffer) and RCAS, as asked,
        and the clamp after either (``TemporalUpscaler._finish_output``)."""
        p = self.params
        if p.back_projection is not None:
            w, h = self.render
            big_w, big_h = self.display
            tx = _kernel_x_tables(w, big_w, jit[0])
            ty = cached_axis_taps(h, big_h, jit[1])
            reg = cached_regular_2x(w, big_w, jit[0]) if self.scale == 2 else None
            steps = self._moving_map(self._steps, p.back_projection, self._moving_step, any_moving)
            area = bool(frame.meta.flags & FrameFlags.AREA_SAMPLES)
            still_c = p.precondition(area, False, self._factor)
            moving_c = p.precondition(area, True, self._factor)
            pre = None
            if still_c > 0.0 or moving_c > 0.0:  # as the torch path: either one is enough
                pre = self._moving_map(self._preconditions, still_c, moving_c, any_moving)
            self._back_project(tx, ty, reg, steps, out, pre)
        stops = p.output_sharpness
        if stops is not None:
            # TemporalUpscaler._finish_output: the same RCAS kernel as FSR 1's.
            kernels.rgb8_to_padded(out, self._rcas_in)
            big_w, big_h = self.display
            fsr1_kernels.rcas_to_rgb8(
                self._rcas_in, np.float32(2.0**-stops), out.reshape(big_h, 3 * big_w)
            )
        if stops is not None or p.back_projection is not None:
            color = np.ascontiguousarray(frame.color, dtype=np.uint8)
            kernels.rgb8_box_3x3(color, self._box_lo, self._box_hi)
            kernels.clamp_rgb8(
                out, self._box_lo, self._box_hi, self._near_x, self._near_y,
                p.output_clamp_slack,
            )  # fmt: skip

    def _moving_map(
        self,
        values: npt.NDArray[np.float32],
        still: float,
        moving_value: float | None,
        any_moving: bool,
    ) -> npt.NDArray[np.float32]:
        """A back-projection setting per render pixel, into ``values`` (h, w)
        (``TemporalUpscaler._moving_map``): ``moving_value`` where the dilated motion is
        not zero, ``still`` elsewhere."""
        values.fill(still)
        if moving_value is not None and any_moving:
            d = self._buf.dilated
            values[(d[0] != 0.0) | (d[1] != 0.0)] = moving_value
        return values

    def _back_project(
        self,
        tx: tuple[I64Array, F32Array, I64Array, F32Array],
        ty: AxisTaps,
        reg: Regular2x | None,
        steps: npt.NDArray[np.float32],
        out: npt.NDArray[np.uint8],
        preconditions: npt.NDArray[np.float32] | None = None,
    ) -> None:
        """``back_projection.back_project`` on the new history (the spare buffer) with the
        kernels, then the history into ``out``; ``tx`` the x tables as
        ``_kernel_x_tables`` gives them; the column passes follow the tables' pattern
        ``reg`` at 2x where there is one; ``preconditions`` (h, w), where given, filter
        the correction first (``back_projection.precondition_filter``)."""
        hist, across = self._spare, self._across
        fx_i, fx_w, bx_i, bx_w = tx
        if reg is None:
            kernels.bp_predict_x(hist, fx_i, fx_w, 0, _NO_TAPS, 0, 0, across)
        else:
            kernels.bp_predict_x(
                hist, fx_i, fx_w, reg.base, reg.forward, reg.r_lo, reg.r_hi, across
            )
        kernels.bp_error(self._buf.raw, ty.forward_index, ty.forward_weight, across, self._error)
        kernels.bp_back_y(self._error, ty.back_index, ty.back_weight, across)
        if preconditions is not None:
            if self._correction is None:
                self._correction = np.zeros_like(hist)
            # The error back along the columns, whole: bp_back_x's sums, not yet added.
            kernels.bp_predict_x(across, bx_i, bx_w, 0, _NO_TAPS, 0, 0, self._correction)
            kernels.precondition_add(
                hist, self._correction, preconditions, steps, self._near_x, self._near_y, out
            )
        elif reg is None:
            kernels.bp_back_x(hist, bx_i, bx_w, steps, self._near_x, self._near_y, across, out)
        else:
            kernels.bp_back_x_2x(
                hist, bx_i, bx_w, reg.offsets, reg.back, reg.q_lo, reg.q_hi, steps,
                self._near_y, across, out,
            )  # fmt: skip

    def _output(self) -> npt.NDArray[np.uint8]:
        """An (H, W, 3) uint8 array nobody else holds: a kept one whose last result was let
        go (only this list refers to it then), else a new one, kept for later frames. A
        fresh 2.7 MB array costs about a millisecond of page faults; callers that copy the
        result into a ring slot (the worker, ``to_uint8``) drop it before the next frame."""
        for buf in self._outputs:
            # References: the list, the loop variable and getrefcount's argument.
            if sys.getrefcount(buf) <= 3:
                return buf
        big_w, big_h = self.display
        buf = np.empty((big_h, big_w, 3), np.uint8)
        if len(self._outputs) < _MAX_KEPT_OUTPUTS:
            self._outputs.append(buf)
        return buf

    def _render_stage(
        self,
        frame: RenderFrame,
        jit: tuple[float, float],
        nf: tuple[float, float] | None,
        mean_weight: np.float32,
    ) -> int:
        """Colour, box, dilated motion and trusted weight of this frame into the render
        buffers, and the state for the next frame (``TemporalUpscaler._render_stage``);
        returns how many pixels have non-zero dilated motion."""
        p, b = self.params, self._buf
        color, depth, motion, mask = self._inputs(frame)
        w, h = self.render
        if nf is None:
            use_lin, lin_a, lin_b = False, 0.0, 0.0
        else:
            near, far = nf
            use_lin, lin_a, lin_b = True, -(far - near) / (near * far), 1.0 / near
        kernels.render_inputs(
            color, depth, motion, mask, self._to_ycocg, use_lin, lin_a, lin_b, 4.0 * max(w, h),
            b.raw, b.lin, b.motion, b.mask,
        )  # fmt: skip
        pjx, pjy = self._prev_jitter
        moving: int = kernels.render_reproject(
            b.raw, float(p.presharpen), b.lin, b.motion, b.mask, self._prev_far, self._weight,
            self._has_history, np.float32(p.reset_weight), np.float32(0.5 + jit[0]),
            np.float32(0.5 + jit[1]),
            np.float32(0.5 + pjx), np.float32(0.5 + pjy), np.float32(1.0 + p.depth_tolerance),
            np.float32(p.dynamic_keep - 1.0), np.float32(p.max_weight),
            np.float32(p.moving_max_weight), b.ycc, b.dilated,
            b.prev_weight,
        )  # fmt: skip
        self._prev_jitter = jit
        kernels.render_finish(
            b.raw, b.lin, b.prev_weight, mean_weight, np.float32(p.max_weight),
            np.float32(p.history_slack(bool(frame.meta.flags & FrameFlags.AREA_SAMPLES))),
            b.lo, b.hi, self._prev_far, self._weight,
        )  # fmt: skip
        return moving

    def _display_stage(self, phase: _Phase, mode: int, out: npt.NDArray[np.uint8]) -> None:
        """The new history into the spare buffer, and ``out``."""
        b = self._buf
        step_x, step_y = self._step
        if isinstance(phase, _BlockedPhase):
            kernels.display_blocked(
                b.ycc, b.lo, b.hi, b.prev_weight, b.dilated, phase.tap_y, phase.frac_y,
                phase.tap_x, phase.frac_x, phase.sub_weight, self._grid_x_base, self._grid_x_off,
                self._grid_y, self._grid_y_off, step_x, step_y, mode,
                self.params.history_catmull_rom, float(self.params.history_sharpen_gain),
                self._history, self._spare, out,
            )  # fmt: skip
        else:
            kernels.display_generic(
                b.ycc, b.lo, b.hi, b.prev_weight, b.dilated, self._near_x, self._near_y,
                phase.grid_x, phase.grid_y, phase.weight_x, phase.weight_y, self._grid_x,
                self._grid_y, step_x, step_y, mode, self.params.history_catmull_rom,
                float(self.params.history_sharpen_gain_fractional), *self._display_per_render,
                self._history, self._spare, out,
            )  # fmt: skip

    def _inputs(self, frame: RenderFrame) -> tuple[npt.NDArray[Any], ...]:
        """The frame's planes as the arrays the kernels take (C-contiguous: they read rows
        flat; ring slots already are, so nothing is copied); the kernels index without
        bounds checks, so mismatched shapes are refused here."""
        w, h = self.render
        color = np.ascontiguousarray(frame.color, dtype=np.uint8)
        depth = np.ascontiguousarray(frame.depth, dtype=np.float32)
        motion = np.ascontiguousarray(frame.motion, dtype=np.float32)
        mask = np.ascontiguousarray(frame.dynamic_mask)
        if mask.dtype == np.bool_:
            mask = mask.view(np.uint8)
        if (
            color.shape != (h, w, 3)
            or depth.shape != (h, w)
            or motion.shape != (h, w, 2)
            or mask.shape != (h, w)
        ):
            raise ValueError(
                f"frame buffers disagree: colour {color.shape}, depth {depth.shape}, "
                f"motion {motion.shape}, dynamic mask {mask.shape}, render size {w}x{h}"
            )
        return color, depth, motion, mask

    # -- per-jitter tables ---------------------------------------------------------------

    def _phase(self, jit: tuple[float, float]) -> _Phase:
        phase = self._phases.get(jit)
        if phase is None:
            if len(self._phases) >= _MAX_CACHED_PHASES:
                self._phases.clear()
            phase = self._blocked_phase(jit) if self.scale > 1 else self._generic_phase(jit)
            self._phases[jit] = phase
        return phase

    def _axis_weights(self, n: int, display: int, render: int, j: float) -> torch.Tensor:
        """``TemporalUpscaler._axis_weights``."""
        p = self.params
        g = ops.axis_weight(n, display, render, j, p.sample_sigma, _CPU, torch.float32)
        return g.clamp_(min=p.min_sample_weight)

    def _blocked_phase(self, jit: tuple[float, float]) -> _BlockedPhase:
        """``ops.phase_taps`` and the sample weights of ``TemporalUpscaler._blocked_inputs``."""
        s, k = self.scale, self.params.reconstruct_sharpness
        w, h = self.render
        taps_x, taps_y = ops.phase_taps(s, jit[0], k), ops.phase_taps(s, jit[1], k)
        gx = self._axis_weights(s, w * s, w, jit[0])
        gy = self._axis_weights(s, h * s, h, jit[1])
        weight = torch.outer(gy, gx)
        return _BlockedPhase(
            np.array([n for n, _ in taps_y], np.int64),
            np.array([f for _, f in taps_y], np.float32),
            np.array([n for n, _ in taps_x], np.int64),
            np.array([f for _, f in taps_x], np.float32),
            _f32(weight),
            np.float32(float(weight.mean())),
        )

    def _generic_phase(self, jit: tuple[float, float]) -> _GenericPhase:
        """``ops.jittered_grid`` per axis and the sample weights of
        ``TemporalUpscaler._generic_inputs``."""
        k = self.params.reconstruct_sharpness
        w, h = self.render
        big_w, big_h = self.display
        # ops.jittered_grid's x depends on the widths only, its y on the heights only.
        gx = ops.jittered_grid(Size(big_w, 1), Size(w, 1), (jit[0], 0.0), k, _CPU, torch.float32)
        gy = ops.jittered_grid(Size(1, big_h), Size(1, h), (0.0, jit[1]), k, _CPU, torch.float32)
        wx = self._axis_weights(big_w, big_w, w, jit[0])
        wy = self._axis_weights(big_h, big_h, h, jit[1])
        return _GenericPhase(
            _f32(gx[0, 0, :, 0]),
            _f32(gy[0, :, 0, 1]),
            _f32(wx),
            _f32(wy),
            np.float32(float(wx.mean() * wy.mean())),
        )
