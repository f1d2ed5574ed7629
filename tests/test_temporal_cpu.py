"""The numba backend of the temporal upscaler against the torch reference: same steps, same outputs.

Both backends run the same float32 arithmetic; the kernels fuse a multiply-add
exactly where torch's vectorized CPU kernels do, and make the same selections
(box, closest depth, trust, clamps), so on these sequences they agree bit for
bit. The tolerances leave room for what could still differ on another CPU or
torch build: the evaluation order inside a BLAS call or a vectorized kernel,
one float32 ulp, which moves an 8-bit rounding only where a value lies on a
half step. Hence: outputs within 1 of 255 and a mean difference far below
one step, histories within 1e-4.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from server.eval.upscalers import _render_frames
from server.frames.frame import FrameFlags, RenderFrame, Size
from server.game.render.transforms import jitter_phase_count
from tests.test_temporal import DISPLAY, RENDER, pattern_frame, poisoned
from upscalers.temporal.params import TemporalParams
from upscalers.temporal.upscaler import TemporalUpscaler

MAX_U8_DIFF = 1
MAX_MEAN_U8_DIFF = 0.01
HISTORY_ATOL = 1e-4


def _backends() -> tuple[TemporalUpscaler, TemporalUpscaler]:
    ref = TemporalUpscaler(device="cpu", backend="torch")
    fast = TemporalUpscaler(device="cpu", backend="numba")
    return ref, fast


def _assert_agree(
    ref: TemporalUpscaler, fast: TemporalUpscaler, a: torch.Tensor, b: torch.Tensor
) -> None:
    assert b.dtype == torch.uint8 and b.shape == a.shape
    diff = (a.int() - b.int()).abs()
    assert int(diff.max()) <= MAX_U8_DIFF
    assert float(diff.float().mean()) < MAX_MEAN_U8_DIFF
    assert ref._history is not None and fast._history is not None
    assert fast._history.shape == ref._history.shape
    assert torch.isfinite(fast._history).all()
    assert torch.allclose(fast._history, ref._history.float(), rtol=0.0, atol=HISTORY_ATOL)
    assert ref._weight is not None and fast._weight is not None
    assert torch.allclose(fast._weight, ref._weight, rtol=0.0, atol=HISTORY_ATOL)


def _run_both(
    frames: list[RenderFrame], display: Size
) -> tuple[TemporalUpscaler, TemporalUpscaler]:
    ref, fast = _backends()
    for f in frames:
        _assert_agree(ref, fast, ref.upscale(f, display), fast.upscale(f, display))
    assert fast._host is not None and ref._host is None  # each ran its own path
    return ref, fast


def _moving_sequence(render: Size, scale: float, n: int = 7) -> list[RenderFrame]:
    """Motion, then two frames where nothing moves (the history is used as it is), then
    motion again; a moving object (dynamic mask) from the third frame on."""
    frames = []
    for i in range(n):
        f = pattern_frame(render, i, scale=scale, motion=0.0 if i in (3, 4) else 0.7)
        if i >= 2:
            w, h = render
            f.dynamic_mask[h // 4 : h // 2, w // 3 : w // 2] = 1
        frames.append(f)
    frames[0] = replace(frames[0], meta=replace(frames[0].meta, flags=FrameFlags.RESET))
    return frames


@pytest.mark.parametrize(
    ("render", "scale"),
    [(RENDER, 2.0), (Size(641, 359), 2.0), (Size(41, 23), 3.0), (Size(40, 24), 4.0),
     (Size(64, 36), 1.0), (Size(161, 89), 1.5), (Size(161, 89), 1.7), (Size(33, 17), 0.5),
     (Size(7, 5), 2.0), (Size(3, 2), 3.0)],
)  # fmt: skip
def test_backends_agree_under_motion(render: Size, scale: float) -> None:
    """Integer scales (the blocked kernel), any other ratio (the generic one)."""
    _run_both(_moving_sequence(render, scale), render.scaled(scale))


@pytest.mark.parametrize(
    ("render", "scale"),
    [(RENDER, 2.0), (Size(41, 23), 3.0), (Size(161, 89), 1.5), (Size(7, 5), 2.0)],
)
def test_backends_agree_on_area_samples(render: Size, scale: float) -> None:
    """Frames flagged AREA_SAMPLES take the preconditioned back-projection (its own
    kernels on the numba side) and the wider history box, still and moving."""
    frames = [
        replace(f, meta=replace(f.meta, flags=f.meta.flags | FrameFlags.AREA_SAMPLES))
        for f in _moving_sequence(render, scale)
    ]
    for f in frames[5:]:  # still and moving pixels in one frame: two strengths
        f.motion[:, : render.width // 2] = 0.0
    _run_both(frames, render.scaled(scale))


@pytest.mark.parametrize("scene", ["slow_pan", "moving_objects"])
def test_backends_agree_on_game_frames(scene: str) -> None:
    frames = _render_frames(scene, Size(160, 90), 2.0, [i / 30 for i in range(6)], True, None)
    if scene == "moving_objects":
        assert any(f.dynamic_mask.any() for f in frames)
    _run_both(frames, Size(320, 180))


def test_backends_agree_on_reset_and_scene_cut() -> None:
    frames = [pattern_frame(RENDER, i, motion=0.3) for i in range(4)]
    cut = pattern_frame(RENDER, 4, flags=FrameFlags.RESET, motion=0.3)
    cut.color[:] = 255 - cut.color
    frames.append(cut)
    frames += [pattern_frame(RENDER, i, motion=0.3) for i in range(5, 7)]
    # A scene cut without the flag: the clamp has to let the new content through.
    for f in frames[-2:]:
        f.color[:] = 30
    ref, fast = _run_both(frames, DISPLAY)
    # reset() itself forgets the numba state too.
    f = pattern_frame(RENDER, 9, motion=0.3)
    ref.reset()
    fast.reset()
    assert fast._history is None
    out = fast.upscale(f, DISPLAY)
    _assert_agree(ref, fast, ref.upscale(f, DISPLAY), out)
    assert torch.equal(out, TemporalUpscaler(device="cpu", backend="numba").upscale(f, DISPLAY))


def test_backends_agree_with_motion_off_screen() -> None:
    frames = [pattern_frame(RENDER, i, motion=0.4) for i in range(6)]
    for k, f in enumerate(frames[3:]):
        w = RENDER.width
        f.motion[:, : w // 3] = 5000.0 * (-1) ** k
        f.motion[:, w // 3 : w // 2, 1] = -90.0
        f.depth[10:20] = 0.01  # a near wall that disoccludes what was behind it
    _run_both(frames, DISPLAY)


@pytest.mark.parametrize("kind", [FrameFlags.NONE, FrameFlags.AREA_SAMPLES], ids=["point", "area"])
def test_backends_agree_on_non_finite_inputs_and_history(kind: FrameFlags) -> None:
    """NaN and Inf in depth, motion and jitter, and planted into both backends' history
    and weight: outputs stay finite and equal, and the next history is clean (also on
    area samples, whose preconditioning spreads a correction to the neighbours)."""
    ref, fast = _backends()
    rng = np.random.default_rng(0)
    for i in range(6):
        f = poisoned(pattern_frame(RENDER, i, motion=0.0 if i == 4 else 0.4), rng, i == 3)
        f.meta = replace(f.meta, flags=f.meta.flags | kind)
        f.depth[1, :5] = -np.inf  # a fresh copy: poisoned copies the planes it changes
        a, b = ref.upscale(f, DISPLAY), fast.upscale(f, DISPLAY)
        _assert_agree(ref, fast, a, b)
        for up in (ref, fast):
            assert up._history is not None and up._weight is not None
            up._history.view(-1)[::7] = float("nan")
            up._history.view(-1)[3::11] = float("inf")
            up._history.view(-1)[5::13] = float("-inf")
            up._weight.view(-1)[::5] = float("nan")
            up._weight.view(-1)[1::9] = float("inf")
    # A last frame without motion takes the history as it is (another sanitizing path).
    f = pattern_frame(RENDER, 9)
    _assert_agree(ref, fast, ref.upscale(f, DISPLAY), fast.upscale(f, DISPLAY))


def test_backends_agree_when_the_jitter_wraps_around() -> None:
    frames = [pattern_frame(RENDER, i, motion=0.25) for i in range(jitter_phase_count(2.0) + 5)]
    _run_both(frames, DISPLAY)


def test_backends_agree_across_size_changes() -> None:
    ref, fast = _backends()
    for i, (render, display) in enumerate(
        [(RENDER, DISPLAY), (RENDER, DISPLAY), (Size(64, 36), DISPLAY), (RENDER, Size(144, 81))]
    ):
        f = pattern_frame(render, i, motion=0.5)
        _assert_agree(ref, fast, ref.upscale(f, display), fast.upscale(f, display))


def test_numba_backend_needs_cpu_and_float32() -> None:
    with pytest.raises(ValueError, match="CPU with float32"):
        TemporalUpscaler(device="cuda", backend="numba")
    with pytest.raises(ValueError, match="CPU with float32"):
        TemporalUpscaler(device="cpu", dtype=torch.float16, backend="numba")
    with pytest.raises(ValueError, match="unknown temporal backend"):
        TemporalUpscaler(device="cpu", backend="jax")


def test_auto_picks_numba_on_the_cpu_with_float32() -> None:
    f = pattern_frame(RENDER, 0)
    auto = TemporalUpscaler(device="cpu")
    auto.upscale(f, DISPLAY)
    assert auto._host is not None
    half = TemporalUpscaler(device="cpu", dtype=torch.float16)
    half.upscale(f, DISPLAY)
    assert half._host is None
    forced = TemporalUpscaler(device="cpu", backend="torch")
    forced.upscale(f, DISPLAY)
    assert forced._host is None


def test_results_the_caller_keeps_are_not_overwritten() -> None:
    """The numba path reuses an output array only once nobody holds its last result."""
    up = TemporalUpscaler(device="cpu", backend="numba")
    kept, copies = [], []
    for i in range(5):
        out = up.upscale(pattern_frame(RENDER, i, motion=0.4), DISPLAY)
        kept.append(out)
        copies.append(out.clone())
        up.upscale(pattern_frame(RENDER, i, motion=0.4), DISPLAY)  # a result let go at once
    assert all(torch.equal(a, b) for a, b in zip(kept, copies, strict=True))


@pytest.mark.parametrize(("h", "w"), [(1, 1), (1, 5), (4, 1), (7, 9), (17, 33)])
def test_the_colour_box_kernel_is_the_torch_box(h: int, w: int) -> None:
    """The separable uint8 3x3 min / max behind the output's clamp, at the edges and on
    images one pixel wide or high."""
    from upscalers.temporal import cpu_kernels as kernels
    from upscalers.temporal import ops

    color = np.random.default_rng(h * 100 + w).integers(0, 256, (h, w, 3), dtype=np.uint8)
    lo, hi = np.zeros_like(color), np.zeros_like(color)
    kernels.rgb8_box_3x3(color, lo, hi)
    ref_lo, ref_hi = ops.box_3x3(torch.from_numpy(color).permute(2, 0, 1).float())
    assert np.array_equal(lo, ref_lo.permute(1, 2, 0).numpy().astype(np.uint8))
    assert np.array_equal(hi, ref_hi.permute(1, 2, 0).numpy().astype(np.uint8))


def _half_moving_sequence(n: int = 5) -> list[RenderFrame]:
    """The pattern moving on the left half only (motion zero on the right half)."""
    frames = [pattern_frame(RENDER, i, motion=0.6) for i in range(n)]
    for f in frames:
        f.motion[:, RENDER.width // 2 :] = 0.0
    return frames


def test_moving_pixels_take_the_moving_step_on_both_backends() -> None:
    """Back-projection's step is ``moving_back_projection`` where the (dilated) motion is
    not zero and ``back_projection`` elsewhere: the backends agree on a half-moving frame,
    and the moving step changes the moving half only."""
    frames = _half_moving_sequence()
    _run_both(frames, DISPLAY)
    outs = []
    for moving_step in (None, 0.8):
        params = TemporalParams(back_projection=0.3, moving_back_projection=moving_step)
        up = TemporalUpscaler(device="cpu", backend="numba", params=params)
        for f in frames:
            out = up.upscale(f, DISPLAY)
        outs.append(out.int())
    q = DISPLAY.width // 4
    diff = (outs[0] - outs[1]).abs()
    assert int(diff[..., :q].max()) > 0  # moving: another step
    assert int(diff[..., 3 * q :].max()) == 0  # still: the same step, the same pixels


def test_the_moving_step_shrinks_above_2x_on_both_backends() -> None:
    """Above ``moving_step_scale`` the moving step is scaled by it over the scale (the
    game's point samples alias more at 3x): both backends take that step there, and agree."""
    p = TemporalParams()
    assert p.moving_back_projection is not None
    assert p.moving_step(1.5) == p.moving_step(2.0) == p.moving_back_projection
    assert p.moving_step(3.0) == pytest.approx(p.moving_back_projection * 2.0 / 3.0)
    display = Size(RENDER.width * 3, RENDER.height * 3)
    frames = _half_moving_sequence()
    _run_both(frames, display)
    explicit = TemporalParams(moving_back_projection=p.moving_step(3.0), moving_step_scale=4.0)
    for backend in ("torch", "numba"):
        outs = []
        for params in (p, explicit, TemporalParams(moving_step_scale=4.0)):
            up = TemporalUpscaler(device="cpu", backend=backend, params=params)  # type: ignore[arg-type]
            for f in frames:
                out = up.upscale(f, display)
            outs.append(out.int())
        assert torch.equal(outs[0], outs[1]), backend  # the scaled step, exactly
        assert not torch.equal(outs[0], outs[2]), backend  # not the unscaled one
