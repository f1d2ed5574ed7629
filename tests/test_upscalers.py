"""The upscaler interface, registry, resamplers, output quantization and the host."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from upscalers import registry
from upscalers.base import Upscaler
from upscalers.host import UpscalerHost
from upscalers.output import quantize_into, to_uint8
from upscalers.sanitize import sanitize_frame


def make_frame(size: Size, seed: int = 0, flags: FrameFlags = FrameFlags.NONE) -> RenderFrame:
    rng = np.random.default_rng(seed)
    w, h = size
    return RenderFrame(
        color=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=rng.random((h, w), dtype=np.float32),
        motion=rng.standard_normal((h, w, 2), dtype=np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(frame_id=seed, camera=Camera.identity(), flags=flags),
    )


def test_registry_lists_and_refuses_unknown() -> None:
    assert {"nearest", "bilinear", "bicubic"} <= set(registry.available())
    with pytest.raises(ValueError, match=r"allowed: .*bilinear"):
        registry.create("lanczos9")


@pytest.mark.parametrize("name", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize(
    ("render", "scale"), [(Size(641, 359), 1.5), (Size(640, 360), 1.7), (Size(321, 179), 4.0),
                          (Size(64, 36), 1.0), (Size(640, 360), 2.0)],
)  # fmt: skip
def test_output_has_display_size(name: str, render: Size, scale: float) -> None:
    display = render.scaled(scale)
    out = registry.create(name).upscale(make_frame(render), display)
    assert out.shape == (3, display.height, display.width)
    img = to_uint8(out)
    assert img.shape == (display.height, display.width, 3) and img.dtype == np.uint8


@pytest.mark.parametrize("name", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize("value", [0, 1, 128, 254, 255])
def test_constant_images_stay_constant(name: str, value: int) -> None:
    frame = make_frame(Size(33, 17))
    frame.color[...] = value
    out = to_uint8(registry.create(name).upscale(frame, Size(66, 34)))
    assert (out == value).all()


def test_nearest_2x_duplicates_pixels() -> None:
    frame = make_frame(Size(8, 6))
    out = to_uint8(registry.create("nearest").upscale(frame, Size(16, 12)))
    assert np.array_equal(out, frame.color.repeat(2, axis=0).repeat(2, axis=1))


def test_bilinear_interpolates_between_neighbours() -> None:
    frame = make_frame(Size(2, 1))
    frame.color[0, 0] = 0
    frame.color[0, 1] = 200
    out = to_uint8(registry.create("bilinear").upscale(frame, Size(4, 1)))[0, :, 0]
    # half-pixel centres: 0, 50, 150, 200
    assert out.tolist() == [0, 50, 150, 200]


def test_read_only_input_is_accepted() -> None:
    frame = make_frame(Size(16, 8))
    frame.color.flags.writeable = False
    with_warnings = registry.create("bicubic").upscale(frame, Size(32, 16))
    assert with_warnings.shape == (3, 16, 32)


def test_quantize_float_handles_nan_inf_and_range() -> None:
    img = torch.tensor([[[float("nan"), float("inf"), -float("inf"), 0.5, 1.7, -0.2]]])
    img = img.expand(3, 1, 6).contiguous()
    out = np.empty((1, 6, 3), np.uint8)
    quantize_into(img, out)
    assert out[0, :, 0].tolist() == [0, 255, 0, 128, 255, 0]


def test_sanitize_replaces_non_finite_and_copies_only_then() -> None:
    clean = make_frame(Size(16, 8))
    same, report = sanitize_frame(clean)
    assert same is clean and report.total == 0
    bad = make_frame(Size(16, 8))
    bad.depth[0, 0] = np.nan
    bad.depth[1, 1] = np.inf
    bad.motion[2, 2, 0] = -np.inf
    bad.motion[3, 3, 1] = 1e30
    bad.meta.jitter = (float("nan"), 0.0)
    bad.depth.flags.writeable = False  # slot views are read-only: must not be written
    fixed, report = sanitize_frame(bad)
    assert report.depth_fixed == 2 and report.motion_fixed == 2 and report.meta_fixed == 1
    assert np.isfinite(fixed.depth).all() and np.isfinite(fixed.motion).all()
    assert fixed.depth[0, 0] == 1.0 and fixed.motion[2, 2, 0] == 0.0
    assert fixed.meta.jitter == (0.0, 0.0)
    assert np.isnan(bad.depth[0, 0]), "the slot's own bytes are left alone"


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, 1e30, -1e30])
@pytest.mark.parametrize("plane", ["depth", "motion"])
def test_sanitize_finds_one_bad_value_alone(plane: str, value: float) -> None:
    """The clean-frame check is a min and a max: one NaN, one Inf or one huge motion
    anywhere must still be found (a NaN among finite values must not hide)."""
    frame = make_frame(Size(17, 9))
    array = frame.depth if plane == "depth" else frame.motion[..., 1]
    array[8, 16] = value
    fixed, report = sanitize_frame(frame)
    huge_depth_is_valid = plane == "depth" and np.isfinite(value)
    assert report.total == (0 if huge_depth_is_valid else 1)
    assert np.isfinite(fixed.depth).all() and np.abs(fixed.motion).max() <= 4 * 17


class _SpyUpscaler(Upscaler):
    name = "spy"
    temporal = True

    def __init__(self) -> None:
        self.resets = 0
        self.seen_finite: list[bool] = []

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        self.seen_finite.append(bool(np.isfinite(frame.depth).all()))
        return torch.zeros((3, display_size.height, display_size.width))

    def reset(self) -> None:
        self.resets += 1


def test_host_resets_on_reset_flag_and_size_change_and_sanitizes() -> None:
    host = UpscalerHost("bilinear", Size(32, 16))
    spy = _SpyUpscaler()
    host.upscaler = spy
    host.upscale(make_frame(Size(16, 8), 0))  # first frame: new size
    # The same picture again: another noise picture would be a scene cut to the host's
    # cut detector (tests/test_cut_detector.py), a reset of its own.
    host.upscale(make_frame(Size(16, 8), 0))
    host.upscale(make_frame(Size(16, 8), 2, FrameFlags.RESET))
    host.upscale(make_frame(Size(8, 4), 3))  # resolution change
    assert spy.resets == 3
    bad = make_frame(Size(8, 4), 4)
    bad.depth[...] = np.nan
    host.upscale(bad)
    assert spy.seen_finite == [True] * 5
    assert host.sanitized_frames == 1 and host.sanitized_values == 32


def test_host_switch_refuses_unknown_and_keeps_current() -> None:
    host = UpscalerHost("bilinear", Size(32, 16))
    with pytest.raises(ValueError):
        host.switch("nope")
    assert host.name == "bilinear"
    host.switch("bicubic")
    assert host.name == "bicubic"
