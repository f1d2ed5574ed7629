"""The temporal upscaler: convergence, resets, robustness to bad values, sizes, CUDA."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from server.game.render.renderer import Renderer, RenderTargets
from server.game.render.transforms import jitter_offset, jitter_phase_count
from upscalers import metrics, registry
from upscalers.output import to_uint8
from upscalers.temporal.params import TemporalParams
from upscalers.temporal.upscaler import TemporalUpscaler

RENDER = Size(96, 54)
DISPLAY = Size(192, 108)


def pattern_frame(
    size: Size,
    index: int,
    *,
    scale: float = 2.0,
    flags: FrameFlags = FrameFlags.NONE,
    motion: float = 0.0,
) -> RenderFrame:
    """A smooth pattern sampled at the jittered positions, moving so that the surface at
    p is at p + (motion, motion) in the previous frame, as the contract says."""
    w, h = size
    jx, jy = jitter_offset(index, jitter_phase_count(scale))
    x = np.arange(w, dtype=np.float32) + 0.5 + jx
    y = np.arange(h, dtype=np.float32)[:, None] + 0.5 + jy
    color = pattern(x + motion * index, y + motion * index)
    return RenderFrame(
        color=np.clip(color * 255.0 + 0.5, 0, 255).astype(np.uint8),
        depth=np.full((h, w), 0.5, np.float32),
        motion=np.full((h, w, 2), motion, np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(index, Camera.identity(), (jx, jy), flags),
    )


def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    base = 0.5 + 0.4 * np.sin(0.9 * x) * np.cos(0.7 * y)
    return np.stack(np.broadcast_arrays(base, 1.0 - base, 0.5 * base + 0.25), -1)


def truth_of(frame: RenderFrame, render: Size, display: Size, motion: float) -> torch.Tensor:
    """The pattern at the display pixel centres, (3, H, W) float, in [0, 1]."""
    i = frame.meta.frame_id
    x = (np.arange(display.width) + 0.5) * render.width / display.width
    y = (np.arange(display.height)[:, None] + 0.5) * render.height / display.height
    return torch.from_numpy(pattern(x + motion * i, y + motion * i)).permute(2, 0, 1).float()


def unit(image: torch.Tensor) -> torch.Tensor:
    """An upscaler's (3, H, W) result as float in [0, 1] (temporal returns uint8)."""
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def run(up: TemporalUpscaler, frames: list[RenderFrame], display: Size) -> torch.Tensor:
    """The last frame's result, as float in [0, 1] on the CPU (the upscaler runs on CUDA
    where there is one)."""
    out = torch.empty(0)
    for f in frames:
        out = up.upscale(f, display)
    return unit(out.cpu())


def test_registered_interface() -> None:
    assert TemporalUpscaler.name == "temporal" and TemporalUpscaler.temporal
    out = TemporalUpscaler().upscale(pattern_frame(RENDER, 0, flags=FrameFlags.RESET), DISPLAY)
    # uint8 sRGB: what ring U holds, so the output costs no float passes at display size.
    assert out.shape == (3, DISPLAY.height, DISPLAY.width) and out.dtype == torch.uint8


@pytest.fixture(scope="module")
def static_scene() -> tuple[list[RenderFrame], np.ndarray]:
    render = Size(96, 54)
    r = Renderer("static", render, scale=2.0)
    frames = [r.render(i, i / 60, RenderTargets.allocate(render)) for i in range(24)]
    truth = r.render_ground_truth(23 / 60, Size(192, 108), supersample=3)
    return frames, truth


def test_static_scene_converges_above_single_frame_and_bilinear(
    static_scene: tuple[list[RenderFrame], np.ndarray],
) -> None:
    frames, truth = static_scene
    up = TemporalUpscaler()
    first = to_uint8(up.upscale(frames[0], DISPLAY))
    last = to_uint8(run(up, frames[1:], DISPLAY))
    bilinear = to_uint8(registry.create("bilinear").upscale(frames[-1], DISPLAY))
    p_last, p_first = metrics.psnr(truth, last), metrics.psnr(truth, first)
    p_bilinear = metrics.psnr(truth, bilinear)
    assert p_last > p_first + 0.5, (p_last, p_first)
    assert p_last > p_bilinear + 1.0, (p_last, p_bilinear)


def test_reset_flag_equals_fresh_instance() -> None:
    up = TemporalUpscaler()
    run(up, [pattern_frame(RENDER, i, motion=0.3) for i in range(5)], DISPLAY)
    cut = pattern_frame(RENDER, 7, flags=FrameFlags.RESET)
    cut.color[:] = 255 - cut.color
    after = up.upscale(cut, DISPLAY)
    fresh = TemporalUpscaler().upscale(cut, DISPLAY)
    assert torch.equal(after, fresh)
    # reset() by itself does the same.
    up2 = TemporalUpscaler()
    run(up2, [pattern_frame(RENDER, i) for i in range(3)], DISPLAY)
    up2.reset()
    plain = replace(cut, meta=replace(cut.meta, flags=FrameFlags.NONE))
    assert torch.equal(up2.upscale(plain, DISPLAY), TemporalUpscaler().upscale(plain, DISPLAY))


def test_history_adds_detail_then_follows_changes() -> None:
    up = TemporalUpscaler()
    run(up, [pattern_frame(RENDER, i) for i in range(8)], DISPLAY)
    # A sudden change without a RESET flag: the neighbourhood clamp lets the new
    # content through within a frame or two.
    changed = [pattern_frame(RENDER, i) for i in range(8, 10)]
    for f in changed:
        f.color[:] = 30
    out = run(up, changed, DISPLAY)
    assert float((out - 30 / 255).abs().max()) < 0.02


def poisoned(frame: RenderFrame, rng: np.random.Generator, bad_jitter: bool) -> RenderFrame:
    """``frame`` with NaN in a tenth of its depth and motion, +-Inf and huge motion in
    places, and (``bad_jitter``) a NaN jitter."""
    depth, motion = frame.depth.copy(), frame.motion.copy()
    depth[rng.random(depth.shape) < 0.1] = np.nan
    depth[0, :5] = np.inf
    motion[rng.random(motion.shape) < 0.1] = np.nan
    motion[3, :4] = [np.inf, -np.inf]
    motion[5, 5] = [1e30, -1e30]
    frame = replace(frame, depth=depth, motion=motion)
    if bad_jitter:
        frame = replace(frame, meta=replace(frame.meta, jitter=(float("nan"), 0.1)))
    return frame


def test_non_finite_inputs_and_history_never_reach_output() -> None:
    up = TemporalUpscaler()
    rng = np.random.default_rng(0)
    for i in range(6):
        f = poisoned(pattern_frame(RENDER, i, motion=0.4), rng, bad_jitter=i == 3)
        out = unit(up.upscale(f, DISPLAY))
        assert torch.isfinite(out).all()
        # Plant NaN and Inf into the history itself.
        assert up._history is not None and up._weight is not None
        up._history.view(-1)[::7] = float("nan")
        up._history.view(-1)[3::11] = float("inf")
        up._weight.view(-1)[::5] = float("nan")
    out = unit(up.upscale(pattern_frame(RENDER, 9, motion=0.4), DISPLAY))
    assert torch.isfinite(out).all() and float(out.min()) >= 0 and float(out.max()) <= 1
    assert up._history is not None and torch.isfinite(up._history).all()


def test_motion_far_off_screen_rejects_history() -> None:
    up = TemporalUpscaler()
    run(up, [pattern_frame(RENDER, i) for i in range(6)], DISPLAY)
    f = pattern_frame(RENDER, 6, motion=5000.0)
    f.color[:] = 200
    out = unit(up.upscale(f, DISPLAY))
    assert torch.isfinite(out).all()
    # No history survives: the output is the current frame (a constant image).
    assert float((out - 200 / 255).abs().max()) < 1e-3
    # The accumulated weight is this frame's alone: a fresh instance's, less what its
    # reset's spatial start carries into later frames.
    fresh = TemporalUpscaler()
    fresh.upscale(f, DISPLAY)
    assert up._weight is not None and fresh._weight is not None
    assert torch.allclose(up._weight + fresh.params.reset_carry, fresh._weight)


def test_disocclusion_drops_history() -> None:
    """Where the previous frame saw something much nearer, history must not be used."""
    up = TemporalUpscaler()
    frames = [pattern_frame(RENDER, i) for i in range(6)]
    for f in frames:
        f.depth[:, :48] = 0.01  # near wall on the left half
        f.color[:, :48] = 0
    run(up, frames, DISPLAY)
    f = pattern_frame(RENDER, 6)
    f.color[:] = 180  # the wall is gone: far surface everywhere
    out = unit(up.upscale(f, DISPLAY))
    assert float((out[:, :, :90] - 180 / 255).abs().max()) < 1e-3


def test_jitter_sequence_wraps_around() -> None:
    up = TemporalUpscaler()
    phases = jitter_phase_count(2.0)
    out = run(up, [pattern_frame(RENDER, i) for i in range(phases + 5)], DISPLAY)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize(
    ("render", "scale"),
    [(Size(161, 89), 1.5), (Size(161, 89), 1.7), (Size(64, 36), 1.0), (Size(40, 24), 4.0),
     (Size(41, 23), 3.0)],
)  # fmt: skip
def test_odd_sizes_and_scales(render: Size, scale: float) -> None:
    display = render.scaled(scale)
    up = TemporalUpscaler()
    frames = [pattern_frame(render, i, scale=scale, motion=0.7) for i in range(4)]
    frames[0] = replace(frames[0], meta=replace(frames[0].meta, flags=FrameFlags.RESET))
    out = run(up, frames, display)
    assert out.shape == (3, display.height, display.width)
    assert torch.isfinite(out).all()
    # The pattern must come out close to itself, whatever the path, and no worse
    # than a bilinear upscale of the same frame.
    truth = truth_of(frames[-1], render, display, 0.7)
    bilinear = registry.create("bilinear").upscale(frames[-1], display).float() / 255
    err = float((out - truth).abs().mean())
    assert err < 0.05 and err < float((bilinear - truth).abs().mean()) + 0.005


def test_constant_image_stays_constant() -> None:
    up = TemporalUpscaler()
    for i in range(5):
        f = pattern_frame(RENDER, i, motion=0.3)
        f.color[:] = 77
        out = to_uint8(up.upscale(f, DISPLAY))
        assert (out == 77).all()


def test_render_size_change_resets() -> None:
    up = TemporalUpscaler()
    run(up, [pattern_frame(RENDER, i) for i in range(3)], DISPLAY)
    small = pattern_frame(Size(64, 36), 3)
    out = up.upscale(small, DISPLAY)
    assert out.shape == (3, DISPLAY.height, DISPLAY.width)
    assert torch.equal(out, TemporalUpscaler().upscale(small, DISPLAY))
    out = up.upscale(pattern_frame(RENDER, 4), Size(144, 81))
    assert out.shape == (3, 81, 144)


def test_float16_history_stays_with_float32_under_motion() -> None:
    """float16 is the history's storage; the arithmetic stays float32, so the drift that
    float16 positions caused (0.2 of full scale after six moving frames) is gone. The
    output's RCAS is off: it would scale the storage's rounding along with the detail."""
    unsharpened = TemporalParams(output_sharpness=None)
    ref = TemporalUpscaler(unsharpened, device="cpu")
    half = TemporalUpscaler(unsharpened, device="cpu", dtype=torch.float16)
    for i in range(8):
        f = pattern_frame(RENDER, i, motion=0.4)
        diff = (unit(ref.upscale(f, DISPLAY)) - unit(half.upscale(f, DISPLAY))).abs()
        assert half._history is not None and half._history.dtype == torch.float16
        assert float(diff.mean()) < 0.5 / 255 and float(diff.max()) <= 2 / 255, i


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_cuda_matches_cpu(dtype: torch.dtype) -> None:
    cpu = TemporalUpscaler(device="cpu")
    gpu = TemporalUpscaler(device="cuda", dtype=dtype)
    frames = [pattern_frame(RENDER, i, motion=0.4) for i in range(6)]
    for f in frames:
        a = unit(cpu.upscale(f, DISPLAY))
        b_raw = gpu.upscale(f, DISPLAY)
        assert b_raw.device.type == "cuda"
        b = unit(b_raw)
        # float16 storage rounds the history each frame (the arithmetic is float32).
        tol_mean, tol_max = (0.5 / 255, 4 / 255) if dtype == torch.float32 else (1 / 255, 4 / 255)
        diff = (a - b.cpu().float()).abs()
        assert float(diff.mean()) < tol_mean and float(diff.max()) < tol_max
