"""The numba CPU kernels of FSR 1 (``upscalers/fsr1_cpu*.py``): the same images as the
torch path to one 8-bit step, the hard cases (flat, black, 0/255-only, odd sizes, scales
1 to 4), and which backend a configuration runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from server.eval.upscalers import _render_frames
from server.frames.frame import Size
from tests.test_fsr1 import make_frame, random_color
from upscalers.fsr1.upscaler import EasuRcasUpscaler, EasuUpscaler
from upscalers.output import to_uint8

FSR = [EasuUpscaler, EasuRcasUpscaler]


def both(make: type, frame_color: np.ndarray, display: Size, **options: object) -> tuple:
    """(numba, torch) results of the same frame, as (H, W, 3) int arrays."""
    frame = make_frame(frame_color)
    fast = make(backend="numba", **options).upscale(frame, display)
    ref = make(backend="torch", **options).upscale(frame, display)
    assert fast.dtype == torch.uint8 and fast.shape == (3, display.height, display.width)
    return to_uint8(fast).astype(int), to_uint8(ref).astype(int)


def assert_same_to_one_step(fast: np.ndarray, ref: np.ndarray) -> None:
    """Float rounding (fastmath, a different summation order) moves a result across a
    rounding boundary on a few values: never by more than one step. Measured on game
    frames: about 1 value in 10^5 at 2x, 1.4 in 10^3 at 1.7x (fast_yaw, EASU alone)."""
    diff = np.abs(fast - ref)
    assert diff.max() <= 1
    assert diff.mean() < 3e-3, diff.mean()


@pytest.mark.parametrize("make", FSR)
@pytest.mark.parametrize(
    ("render", "scale"),
    [(Size(64, 36), 1.0), (Size(64, 36), 1.5), (Size(64, 36), 1.7), (Size(64, 36), 2.0),
     (Size(641, 359), 2.0), (Size(161, 89), 3.0), (Size(161, 89), 4.0), (Size(40, 24), 2.5)],
)  # fmt: skip
def test_numba_matches_torch_on_noise(make: type, render: Size, scale: float) -> None:
    fast, ref = both(make, random_color(render, seed=11), render.scaled(scale))
    assert_same_to_one_step(fast, ref)


@pytest.mark.parametrize("make", FSR)
@pytest.mark.parametrize("scene", ["thin_detail", "fast_yaw"])
def test_numba_matches_torch_on_game_frames(make: type, scene: str) -> None:
    frame = _render_frames(scene, Size(320, 180), 2.0, [0.2], False, None)[0]
    for display in (Size(640, 360), Size(544, 306)):  # 2x and 1.7x
        fast, ref = both(make, np.asarray(frame.color), display)
        assert_same_to_one_step(fast, ref)


@pytest.mark.parametrize("make", FSR)
@pytest.mark.parametrize("value", [0, 1, 128, 254, 255])
def test_flat_images_stay_exactly_flat(make: type, value: int) -> None:
    """EASU's direction and length divide by zero-sized differences here."""
    color = np.full((17, 33, 3), value, np.uint8)
    for display in (Size(66, 34), Size(50, 26), Size(33, 17)):
        out = make(backend="numba").upscale(make_frame(color), display)
        assert (out == value).all()


@pytest.mark.parametrize("make", FSR)
def test_extreme_values_stay_extreme(make: type) -> None:
    rng = np.random.default_rng(3)
    color = (rng.integers(0, 2, (24, 40, 3)) * 255).astype(np.uint8)  # only 0 and 255
    color[:, :20] = 0
    for display in (Size(80, 48), Size(68, 41)):
        fast, ref = both(make, color, display)
        assert_same_to_one_step(fast, ref)
        assert (fast[:, : display.width // 3] == 0).all()  # black stays black


def test_read_only_ring_slot_views_are_accepted() -> None:
    color = random_color(Size(48, 32), seed=12)
    color.setflags(write=False)
    out = EasuRcasUpscaler().upscale(make_frame(color), Size(96, 64))
    assert out.shape == (3, 64, 96)


def test_each_call_returns_a_fresh_image() -> None:
    """A caller may keep a result while the next frame is upscaled (the layer cache and
    the frame predictor keep theirs)."""
    up = EasuRcasUpscaler()
    first = up.upscale(make_frame(random_color(Size(32, 20), seed=1)), Size(64, 40))
    kept = first.clone()
    up.upscale(make_frame(random_color(Size(32, 20), seed=2)), Size(64, 40))
    assert torch.equal(first, kept)


def test_sharpness_reaches_the_kernel() -> None:
    color = random_color(Size(40, 24), seed=5)
    base = to_uint8(EasuUpscaler().upscale(make_frame(color), Size(80, 48))).astype(int)
    change = [
        np.abs(
            to_uint8(EasuRcasUpscaler(sharpness=s).upscale(make_frame(color), Size(80, 48))) - base
        ).mean()
        for s in (0.0, 1.0, 4.0)
    ]
    assert change[0] > change[1] > change[2]


@pytest.mark.parametrize("make", FSR)
def test_backend_choice(make: type) -> None:
    assert make().backend == "numba"  # the CPU default
    assert make(backend="torch").backend == "torch"
    assert make(dtype=torch.float16).backend == "torch"
    with pytest.raises(ValueError, match="backend"):
        make(backend="cuda")
    with pytest.raises(ValueError, match="float32"):
        make(backend="numba", dtype=torch.float16)


def test_options_the_kernels_lack_run_torch() -> None:
    assert EasuRcasUpscaler(denoise=True).backend == "torch"
    assert EasuRcasUpscaler(compile=True).backend == "torch"
    with pytest.raises(ValueError, match="denoise"):
        EasuRcasUpscaler(denoise=True, backend="numba")
