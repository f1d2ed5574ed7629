"""The API for users: upscalers.upscale_image and upscale_sequence (upscalers/api.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import torch

from server.frames.frame import Size
from server.game.render.transforms import halton
from upscalers import registry, upscale_image, upscale_sequence
from upscalers.api_checks import SizeOrScale
from upscalers.metrics import psnr

METHODS = registry.available()


def _levels(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8]) -> int:
    return int(np.abs(a.astype(np.int16) - b.astype(np.int16)).max())


@pytest.mark.parametrize("method", METHODS)
def test_every_method_takes_odd_sizes_one_pixel_and_both_colour_forms(method: str) -> None:
    rng = np.random.default_rng(0)
    for h, w in ((17, 23), (1, 1)):
        image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        out = upscale_image(image, 2, method=method)
        assert out.shape == (2 * h, 2 * w, 3) and out.dtype == np.uint8
        assert out.flags.c_contiguous and not np.shares_memory(out, image)
        # The same picture as float in [0, 1] (the spatial and the temporal/network
        # methods alike: the range each computes in is the API's business, not the user's).
        as_float = image / 255.0
        assert _levels(upscale_image(as_float, 2, method=method), out) <= 1
        assert _levels(upscale_image(as_float.astype(np.float32), 2, method=method), out) <= 1
        flipped = image[::-1, ::-1, ::-1]  # a view with negative strides (BGR -> RGB, say)
        flipped_out = upscale_image(flipped, 2, method=method)
        assert np.array_equal(flipped_out, upscale_image(flipped.copy(), 2, method=method))
        flat = upscale_image(np.full((h, w, 3), 77, np.uint8), (2 * w + 1, 2 * h + 3), method)
        assert flat.shape == (2 * h + 3, 2 * w + 1, 3)
        assert flat.min() >= 76 and flat.max() <= 78


def test_size_forms_give_the_same_output() -> None:
    image = np.random.default_rng(1).integers(0, 256, (9, 16, 3), dtype=np.uint8)
    by_scale = upscale_image(image, 2.0, "bicubic")
    forms: list[SizeOrScale] = [(32, 18), Size(32, 18), "32x18", 2, np.float32(2.0)]
    for form in forms:
        assert np.array_equal(upscale_image(image, form, "bicubic"), by_scale)
    assert upscale_image(image, 1, "bicubic").shape == image.shape  # scale 1: same size
    assert upscale_image(image, 1.5, "bilinear").shape == (14, 24, 3)  # Size.scaled rounds


def test_options_reach_the_method() -> None:
    image = np.random.default_rng(2).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    soft = upscale_image(image, 2, "easu_rcas", sharpness=2.0)
    sharp = upscale_image(image, 2, "easu_rcas", sharpness=0.0)
    assert _levels(soft, sharp) > 0
    with pytest.raises(ValueError, match=r"takes no option radius; allowed: .*sharpness"):
        upscale_image(image, 2, "easu_rcas", radius=3)


GOOD = np.zeros((4, 6, 3), np.uint8)


@pytest.mark.parametrize(
    ("image", "error", "message"),
    [
        ([[[0, 0, 0]]], TypeError, r"numpy array \(H, W, 3\), got a builtins.list"),
        (torch.zeros(4, 6, 3), TypeError, r"got a torch.Tensor .*image.cpu\(\).numpy\(\)"),
        (np.zeros((4, 6), np.uint8), ValueError, r"\(H, W, 3\), got shape \(4, 6\); a grey image"),
        (np.zeros((4, 6, 4), np.uint8), ValueError, r"got shape \(4, 6, 4\); RGBA"),
        (np.zeros((3, 4, 6), np.uint8), ValueError, r"got shape \(3, 4, 6\); channels first"),
        (np.zeros((0, 6, 3), np.uint8), ValueError, r"at least one pixel, got shape \(0, 6, 3\)"),
        (np.zeros((4, 6, 3), np.uint16), TypeError,
         r"uint8 in 0..255 or float32/float64 in \[0, 1\], got dtype uint16"),
        (np.zeros((4, 6, 3), np.float16), TypeError, r"got dtype float16"),
        (np.full((4, 6, 3), 200.0), ValueError,
         r"in \[0, 1\], got values from 200 to 200 \(it looks like 0..255"),
        (np.full((4, 6, 3), -0.01), ValueError, r"in \[0, 1\], got values from -0.01 to -0.01$"),
        (np.full((4, 6, 3), np.nan, np.float32), ValueError, r"must be finite, got NaN or Inf"),
        (np.full((4, 6, 3), np.inf), ValueError, r"must be finite"),
    ],
)  # fmt: skip
def test_a_wrong_image_says_what_was_expected_and_what_came(
    image: Any, error: type[Exception], message: str
) -> None:
    with pytest.raises(error, match=message):
        upscale_image(image, 2, "bilinear")


def test_float_a_rounding_error_outside_the_range_passes() -> None:
    """1 + 1e-6 is float arithmetic, not a wrong convention: it becomes 255."""
    image = np.full((2, 2, 3), 1.0 + 1e-6, np.float32)
    image[0, 0] = -1e-6
    out = upscale_image(image, 1, "nearest")
    assert out[0, 0].tolist() == [0, 0, 0] and (out[1:] == 255).all()


@pytest.mark.parametrize(
    ("size_or_scale", "error", "message"),
    [
        (0.5, ValueError, r"scale must be a finite number >= 1 \(upscaling only\), got 0.5"),
        (float("nan"), ValueError, r"scale must be a finite number >= 1"),
        ((5, 8), ValueError, r"size 5x8 \(width x height\) is smaller than the image, 6x4"),
        ("3x3", ValueError, r"smaller than the image"),
        ((0, 8), ValueError, r"size must be positive \(width, height\), got \(0, 8\)"),
        ("big", ValueError, r"size must look like 640x360, got 'big'"),
        (True, TypeError, r"size_or_scale must be a scale >= 1 .* got True"),
        ((12.0, 8.0), TypeError, r"size_or_scale must be .*\(width, height\)"),
        (None, TypeError, r"size_or_scale must be"),
    ],
)  # fmt: skip
def test_a_wrong_size_or_scale_says_the_forms(
    size_or_scale: Any, error: type[Exception], message: str
) -> None:
    with pytest.raises(error, match=message):
        upscale_image(GOOD, size_or_scale, "bilinear")


def test_an_unknown_method_lists_the_registry() -> None:
    with pytest.raises(ValueError, match=r"'fsr9'; allowed: bicubic, bilinear, cv_area, cv_cubic"):
        upscale_image(GOOD, 2, "fsr9")
    with pytest.raises(ValueError, match="unknown upscaler 'fsr9'"):
        upscale_sequence([GOOD], 2, "fsr9")  # at the call, before any frame is asked for


# A jittered, panning camera over a detailed picture, sampled at half resolution: what a
# game gives a temporal upscaler, with an exact ground truth at display size.
SCALE, W, H, FRAMES = 2, 48, 32, 16
_rng = np.random.default_rng(0)
_WORLD = cv2.GaussianBlur(_rng.random((H * SCALE + 8, W * SCALE + 40, 3)), (0, 0), 1.0)
WORLD = ((_WORLD - _WORLD.min()) / (_WORLD.max() - _WORLD.min())).astype(np.float32)
JITTER = [(halton(k + 1, 2) - 0.5, halton(k + 1, 3) - 0.5) for k in range(FRAMES)]


def _render(k: int, pan: float, jitter: tuple[float, float]) -> npt.NDArray[np.float32]:
    """Frame ``k``: content moved right by ``pan`` render pixels a frame; pixel (i, j)
    sampled at (i + 0.5 + jx, j + 0.5 + jy)."""
    jx, jy = jitter
    xs = (np.arange(W) + 0.5 + jx) * SCALE - 0.5 - k * pan * SCALE + 20
    ys = (np.arange(H) + 0.5 + jy) * SCALE - 0.5 + 4
    map_x = np.broadcast_to(xs[None, :], (H, W)).astype(np.float32)
    map_y = np.broadcast_to(ys[:, None], (H, W)).astype(np.float32)
    return np.asarray(cv2.remap(WORLD, map_x, map_y, cv2.INTER_LINEAR), dtype=np.float32)


def _truth(k: int, pan: float) -> npt.NDArray[np.uint8]:
    shift = round(k * pan * SCALE)
    view = WORLD[4 : 4 + H * SCALE, 20 - shift : 20 - shift + W * SCALE]
    return np.asarray(np.rint(view * 255.0), dtype=np.uint8)


def _score(image: npt.NDArray[np.uint8], pan: float) -> float:
    inner = slice(4, -4)  # the view's edges have no history to gather from
    return psnr(_truth(FRAMES - 1, pan)[inner, inner], image[inner, inner])


def test_sequence_with_motion_and_jitter_feeds_the_temporal_method() -> None:
    pan = 0.5  # render pixels a frame: one display pixel
    frames = [_render(k, pan, JITTER[k]) for k in range(FRAMES)]
    motion = [np.full((H, W, 2), (-pan, 0.0), np.float32) for _ in range(FRAMES)]
    outs = list(upscale_sequence(frames, SCALE, "temporal", motion=motion, jitter=JITTER))
    assert len(outs) == FRAMES and all(o.shape == (H * SCALE, W * SCALE, 3) for o in outs)
    with_motion = _score(outs[-1], pan)
    without = _score(list(upscale_sequence(frames, SCALE, "temporal", jitter=JITTER))[-1], pan)
    # The spatial baseline gets the unjittered frame, as the stream gives spatial methods.
    single = _score(upscale_image(_render(FRAMES - 1, pan, (0.0, 0.0)), SCALE, "bicubic"), pan)
    # Measured: 28.4 dB with motion, 17.8 without (history smeared), bicubic 26.5.
    assert with_motion > without + 5.0
    assert with_motion > single + 1.0


def test_sequence_jitter_gathers_detail_a_still_camera_cannot() -> None:
    jittered = [_render(k, 0.0, JITTER[k]) for k in range(FRAMES)]
    still = [_render(k, 0.0, (0.0, 0.0)) for k in range(FRAMES)]
    gathered = _score(list(upscale_sequence(jittered, SCALE, "temporal", jitter=JITTER))[-1], 0.0)
    plain = _score(list(upscale_sequence(still, SCALE, "temporal"))[-1], 0.0)
    # Measured: 29.7 dB against 23.1 (and bicubic 26.5).
    assert gathered > plain + 3.0


def test_sequence_of_a_spatial_method_is_each_image_alone() -> None:
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (7, 5, 3), dtype=np.uint8) for _ in range(3)]
    outs = list(upscale_sequence(iter(frames), 3, "easu_rcas"))
    for frame, out in zip(frames, outs, strict=True):
        assert np.array_equal(out, upscale_image(frame, 3, "easu_rcas"))


def test_sequence_errors_name_the_frame() -> None:
    frames = [GOOD, GOOD, GOOD]
    short = [np.zeros((4, 6, 2), np.float32)] * 2
    with pytest.raises(ValueError, match="motion has fewer entries than frames: none for frame 2"):
        list(upscale_sequence(frames, 2, "temporal", motion=short))
    with pytest.raises(ValueError, match="jitter has more entries than the 3 frames"):
        list(upscale_sequence(frames, 2, "temporal", jitter=JITTER[:4]))
    bad_motion = [np.zeros((4, 6, 2), np.float32), np.zeros((6, 4, 2), np.float32)]
    with pytest.raises(ValueError, match=r"motion of frame 1 must have shape \(4, 6, 2\)"):
        list(upscale_sequence(frames[:2], 2, "temporal", motion=bad_motion))
    with pytest.raises(TypeError, match="depth of frame 0 must be float, got dtype uint8"):
        list(upscale_sequence(frames[:1], 2, "temporal", depth=[np.zeros((4, 6), np.uint8)]))
    with pytest.raises(ValueError, match=r"jitter of frame 0 must be in render pixels.*\(1, 0\)"):
        list(upscale_sequence(frames[:1], 2, "temporal", jitter=[(1.0, 0.0)]))
    with pytest.raises(TypeError, match=r"jitter of frame 0 must be two numbers"):
        list(upscale_sequence(frames[:1], 2, "temporal", jitter=[0.25]))  # type: ignore[list-item]
    with pytest.raises(ValueError, match=r"frame 1 must be RGB of shape \(H, W, 3\)"):
        list(upscale_sequence([GOOD, GOOD[..., 0]], 2, "bilinear"))


def test_non_finite_motion_and_depth_are_sanitized_as_in_the_stream() -> None:
    frames = [_render(k, 0.0, JITTER[k]) for k in range(4)]
    bad = np.zeros((H, W, 2), np.float32)
    bad[3, 4] = np.nan
    depth = np.full((H, W), np.inf, np.float32)
    # Flipped views too: planes with negative strides are made contiguous at the edge.
    motion, depths = [bad[::-1, ::-1]] * 4, [depth[::-1]] * 4
    outs = list(upscale_sequence(frames, SCALE, "temporal", motion=motion, depth=depths))
    torch_path = upscale_sequence(
        frames, SCALE, "temporal", motion=motion, depth=depths, backend="torch"
    )
    assert _levels(list(torch_path)[-1], outs[-1]) <= 1
    clean = list(upscale_sequence(frames, SCALE, "temporal"))
    assert _levels(outs[-1], clean[-1]) == 0  # NaN motion -> 0, Inf depth -> 1 (the default)


def test_importing_upscalers_does_not_import_torch() -> None:
    """The relay's base install imports upscalers.names; the API loads on first use."""
    code = (
        "import sys, upscalers, upscalers.names\n"
        "assert 'torch' not in sys.modules and 'cv2' not in sys.modules, sys.modules.keys()\n"
        "assert callable(upscalers.upscale_image) and 'torch' in sys.modules\n"
        "try:\n    upscalers.no_such_thing\nexcept AttributeError:\n    pass\n"
        "else:\n    raise SystemExit('no AttributeError')\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_the_readme_example_runs_as_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from PIL import Image

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("## Upscale your own images", 1)[1]
    example = section.split("```python\n", 1)[1].split("```", 1)[0]
    assert len([line for line in example.splitlines() if line.strip()]) == 5
    monkeypatch.chdir(tmp_path)
    Image.fromarray(np.random.default_rng(5).integers(0, 256, (9, 13, 3), np.uint8)).save(
        "shot.png"
    )
    exec(compile(example, "README.md", "exec"), {})
    assert Image.open("shot_2x.png").size == (26, 18)


def _render_area(jitter: tuple[float, float]) -> npt.NDArray[np.float32]:
    """A still camera's frame as a camera or a downscale by area makes it: each pixel
    the average of the picture over its footprint, the footprints moved by ``jitter``."""
    jx, jy = jitter
    xs = np.arange(W * SCALE) + jx * SCALE + 20
    ys = np.arange(H * SCALE) + jy * SCALE + 4
    map_x = np.broadcast_to(xs[None, :], (H * SCALE, W * SCALE)).astype(np.float32)
    map_y = np.broadcast_to(ys[:, None], (H * SCALE, W * SCALE)).astype(np.float32)
    shifted = cv2.remap(WORLD, map_x, map_y, cv2.INTER_LINEAR)
    return np.asarray(cv2.resize(shifted, (W, H), interpolation=cv2.INTER_AREA), np.float32)


def test_sequence_of_area_samples_says_so_and_gains() -> None:
    """``area_samples=True`` tells the temporal method its input is box averages, which
    it can undo faster: closer to the truth than the same frames taken as point samples."""
    frames = [_render_area(JITTER[k]) for k in range(FRAMES)]
    area = list(upscale_sequence(frames, SCALE, "temporal", jitter=JITTER, area_samples=True))
    point = list(upscale_sequence(frames, SCALE, "temporal", jitter=JITTER))
    assert np.array_equal(area[0], point[0])  # the first frame has no history to refine
    gain = _score(area[-1], 0.0) - _score(point[-1], 0.0)
    assert gain > 0.3, gain
