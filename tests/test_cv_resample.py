"""OpenCV's resize behind the upscaler interface (cv_*), and bilinear's OpenCV path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from server.frames.frame import Camera, FrameMeta, RenderFrame, Size
from upscalers import names, registry
from upscalers.output import to_uint8
from upscalers.spatial.resample import BilinearUpscaler, NearestUpscaler, color_as_nchw

CV_METHODS = {
    "cv_cubic": cv2.INTER_CUBIC,
    "cv_lanczos4": cv2.INTER_LANCZOS4,
    "cv_area": cv2.INTER_AREA,
}


def make_frame(size: Size, seed: int = 0) -> RenderFrame:
    rng = np.random.default_rng(seed)
    w, h = size
    return RenderFrame(
        color=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=np.ones((h, w), np.float32),
        motion=np.zeros((h, w, 2), np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(frame_id=seed, camera=Camera.identity()),
    )


def test_cv_methods_are_registered_and_named_without_torch() -> None:
    for name in CV_METHODS:
        assert name in registry.available() and name in names.UPSCALERS
        assert not registry.is_temporal(name)


@pytest.mark.parametrize("name", sorted(CV_METHODS))
@pytest.mark.parametrize(
    ("render", "display"),
    [(Size(640, 360), Size(1280, 720)), (Size(37, 23), Size(111, 53)), (Size(1, 1), Size(3, 2)),
     (Size(64, 36), Size(64, 36))],
)  # fmt: skip
def test_cv_method_is_cv2_resize(name: str, render: Size, display: Size) -> None:
    frame = make_frame(render)
    frame.color.flags.writeable = False  # ring slots are read-only views
    out = registry.create(name).upscale(frame, display)
    assert out.shape == (3, display.height, display.width) and out.dtype == torch.uint8
    expected = cv2.resize(frame.color, display, interpolation=CV_METHODS[name])
    assert np.array_equal(to_uint8(out), expected)


@pytest.mark.parametrize("name", sorted(CV_METHODS))
@pytest.mark.parametrize("value", [0, 1, 254, 255])
def test_cv_constant_images_stay_constant(name: str, value: int) -> None:
    frame = make_frame(Size(33, 17))
    frame.color[...] = value
    assert (to_uint8(registry.create(name).upscale(frame, Size(66, 34))) == value).all()


def _torch_bilinear(color: np.ndarray, size: Size) -> np.ndarray:
    out = F.interpolate(
        color_as_nchw(color), size=(size.height, size.width), mode="bilinear", align_corners=False
    )
    return np.asarray(out[0].permute(1, 2, 0))


@pytest.mark.parametrize(
    ("render", "display"),
    [(Size(640, 360), Size(1280, 720)), (Size(854, 480), Size(1280, 720)),
     (Size(427, 240), Size(1280, 720)), (Size(37, 23), Size(111, 53)), (Size(1, 5), Size(2, 11)),
     (Size(640, 360), Size(500, 301))],
)  # fmt: skip
def test_bilinear_opencv_path_matches_torch_within_one_level(render: Size, display: Size) -> None:
    """The CPU path switched to OpenCV only because it gives the same images: every
    pixel, borders included, within one level of F.interpolate (random colour is the
    worst case: neighbours differ by up to 255)."""
    frame = make_frame(render, seed=3)
    fast = registry.create("bilinear")
    assert isinstance(fast, BilinearUpscaler) and fast.backend == "opencv"
    out = to_uint8(fast.upscale(frame, display))
    reference = _torch_bilinear(frame.color, display)
    assert np.abs(out.astype(np.int16) - reference).max() <= 1
    torch_path = to_uint8(registry.create("bilinear", backend="torch").upscale(frame, display))
    assert np.array_equal(torch_path, reference)


def test_bilinear_refuses_an_unknown_backend() -> None:
    with pytest.raises(ValueError, match="backend must be one of auto, torch"):
        registry.create("bilinear", backend="numba")


@pytest.mark.parametrize(
    ("render", "display", "library"),
    [(Size(640, 360), Size(1280, 720), True), (Size(427, 240), Size(1281, 720), True),
     (Size(37, 23), Size(296, 46), True), (Size(1, 1), Size(8, 3), True),
     (Size(5, 3), Size(5, 3), True), (Size(853, 480), Size(1280, 720), False),
     (Size(10, 10), Size(90, 20), False), (Size(37, 23), Size(111, 53), False)],
)  # fmt: skip
def test_nearest_takes_opencv_only_at_whole_multiples_and_gives_torch_s_bits(
    render: Size, display: Size, library: bool
) -> None:
    """1.5x (853 -> 1280) is where OpenCV breaks ties the other way: torch keeps it; 9x
    is beyond the factors checked."""
    nearest = registry.create("nearest")
    assert isinstance(nearest, NearestUpscaler)
    assert nearest.library_serves(render, display) is library
    frame = make_frame(render, seed=4)
    out = to_uint8(nearest.upscale(frame, display))
    reference = F.interpolate(
        color_as_nchw(frame.color), size=(display.height, display.width), mode="nearest-exact"
    )
    assert np.array_equal(out, np.asarray(reference[0].permute(1, 2, 0)))
    torch_path = registry.create("nearest", backend="torch").upscale(frame, display)
    assert np.array_equal(to_uint8(torch_path), out)


def test_opencv_exact_nearest_does_break_1_5x_ties_differently() -> None:
    """Why nearest keeps torch off whole multiples (if this starts to pass as equal, the
    condition in NearestUpscaler.library_serves can widen)."""
    frame = make_frame(Size(853, 480), seed=5)
    ours = to_uint8(registry.create("nearest").upscale(frame, Size(1280, 720)))
    theirs = cv2.resize(frame.color, (1280, 720), interpolation=cv2.INTER_NEAREST_EXACT)
    assert not np.array_equal(ours, theirs)
