"""FSR 1 (EASU, RCAS) and Lanczos-2: exactness against a per-pixel transcription of
the FSR math, invariants (flat stays flat, de-ringing, [0, 1]), shapes, sharpness."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from functools import partial

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from server.frames.frame import Camera, FrameMeta, RenderFrame, Size
from upscalers.base import Upscaler
from upscalers.fsr1.easu import Easu
from upscalers.fsr1.rcas import RCAS_LIMIT, Rcas
from upscalers.fsr1.upscaler import EasuRcasUpscaler, EasuUpscaler
from upscalers.output import to_uint8
from upscalers.spatial.lanczos import Lanczos2Upscaler

# The float results of the torch path (the reference and the CUDA path); the numba CPU
# kernels, which return 8-bit results, are compared with it in test_fsr1_cpu.py.
TorchEasu = partial(EasuUpscaler, backend="torch")
TorchEasuRcas = partial(EasuRcasUpscaler, backend="torch")

TAPS = ((0, -1), (1, -1), (-1, 0), (0, 0), (1, 0), (2, 0),
        (-1, 1), (0, 1), (1, 1), (2, 1), (0, 2), (1, 2))  # fmt: skip


def make_frame(color: np.ndarray) -> RenderFrame:
    h, w, _ = color.shape
    return RenderFrame(
        color=color,
        depth=np.ones((h, w), np.float32),
        motion=np.zeros((h, w, 2), np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(frame_id=0, camera=Camera.identity()),
    )


def random_color(size: Size, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (size.height, size.width, 3), dtype=np.uint8)


def chw(color: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(color).permute(2, 0, 1).float().div(255.0).contiguous()


def easu_reference(img: np.ndarray, ho: int, wo: int) -> np.ndarray:
    """FsrEasuF transcribed pixel by pixel in float64 (exact rcp/rsqrt, clamp-to-edge)."""
    h, w, _ = img.shape

    def tex(x: int, y: int) -> np.ndarray:
        return np.asarray(img[min(max(y, 0), h - 1), min(max(x, 0), w - 1)])

    def luma(x: int, y: int) -> float:
        c = tex(x, y)
        return float(0.5 * c[0] + c[1] + 0.5 * c[2])

    out = np.zeros((ho, wo, 3))
    for oy in range(ho):
        for ox in range(wo):
            px, py = (ox + 0.5) * w / wo - 0.5, (oy + 0.5) * h / ho - 0.5
            fx, fy = math.floor(px), math.floor(py)
            ppx, ppy = px - fx, py - fy
            dir_x = dir_y = length = 0.0
            quad = ((0, 0, (1 - ppx) * (1 - ppy)), (1, 0, ppx * (1 - ppy)),
                    (0, 1, (1 - ppx) * ppy), (1, 1, ppx * ppy))  # fmt: skip
            for cx, cy, bw in quad:
                x, y = fx + cx, fy + cy
                a, b, c = luma(x, y - 1), luma(x - 1, y), luma(x, y)
                d, e = luma(x + 1, y), luma(x, y + 1)
                for before, after in ((b, d), (a, e)):
                    m = max(abs(after - c), abs(c - before))
                    r = min(1.0, abs(after - before) / m) if m > 0 else 0.0
                    length += r * r * bw
                dir_x += (d - b) * bw
                dir_y += (e - a) * bw
            r2 = dir_x * dir_x + dir_y * dir_y
            if r2 < 1.0 / 32768.0:
                dir_x, inv = 1.0, 1.0
            else:
                inv = 1.0 / math.sqrt(r2)
            dir_x, dir_y = dir_x * inv, dir_y * inv
            length = (length * 0.5) ** 2
            stretch = (dir_x**2 + dir_y**2) / max(abs(dir_x), abs(dir_y))
            lx, ly = 1 + (stretch - 1) * length, 1 - 0.5 * length
            lob = 0.5 + (0.25 - 0.04 - 0.5) * length
            acc, acc_w = np.zeros(3), 0.0
            for tx, ty in TAPS:
                offx, offy = tx - ppx, ty - ppy
                vx = (offx * dir_x + offy * dir_y) * lx
                vy = (-offx * dir_y + offy * dir_x) * ly
                d2 = min(vx * vx + vy * vy, 1.0 / lob)
                wt = (25 / 16 * (2 / 5 * d2 - 1) ** 2 - 9 / 16) * (lob * d2 - 1) ** 2
                acc += tex(fx + tx, fy + ty) * wt
                acc_w += wt
            q = np.stack([tex(fx, fy), tex(fx + 1, fy), tex(fx, fy + 1), tex(fx + 1, fy + 1)])
            out[oy, ox] = np.clip(acc / acc_w, q.min(0), q.max(0))
    return out


def rcas_reference(img: np.ndarray, sharpness: float) -> np.ndarray:
    """FsrRcasF on an (H, W, 3) float64 image, edge-replicated, without noise removal."""
    p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    n, s, w_, e = p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]
    c = p[1:-1, 1:-1]
    mn = np.minimum(np.minimum(n, s), np.minimum(w_, e))
    mx = np.maximum(np.maximum(n, s), np.maximum(w_, e))
    hit_min = mn / (4.0 * mx)
    hit_max = (1.0 - mx) / (4.0 * mn - 4.0)
    lobe = np.maximum(-hit_min, hit_max).max(axis=2, keepdims=True)
    lobe = np.maximum(-RCAS_LIMIT, np.minimum(lobe, 0.0)) * 2.0 ** (-sharpness)
    return np.asarray(np.clip((lobe * (n + s + w_ + e) + c) / (4.0 * lobe + 1.0), 0.0, 1.0))


# --- exactness against the transcription -------------------------------------------------


@pytest.mark.parametrize(
    ("size", "out"),
    [(Size(13, 9), Size(26, 18)), (Size(11, 7), Size(19, 12)), (Size(8, 5), Size(32, 20)),
     (Size(9, 6), Size(14, 9)), (Size(6, 6), Size(6, 6))],
)  # fmt: skip
def test_easu_matches_per_pixel_transcription(size: Size, out: Size) -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (size.height, size.width, 3)).astype(np.float64) / 255.0
    yy, xx = np.mgrid[0 : size.height, 0 : size.width]
    edges = ((0.7 * xx + 0.3 * yy) > size.width / 2)[..., None] * np.array([0.9, 0.5, 0.2]) + 0.05
    for image in (img, edges):
        ref = easu_reference(image, out.height, out.width)
        got = Easu()(torch.from_numpy(image).float().permute(2, 0, 1), (out.height, out.width))
        np.testing.assert_allclose(got.permute(1, 2, 0).numpy(), ref, atol=2e-6)


def test_rcas_matches_per_pixel_transcription() -> None:
    rng = np.random.default_rng(2)
    img = rng.uniform(0.02, 0.98, (12, 17, 3))
    for sharpness in (0.0, 0.2, 1.0):
        padded = torch.zeros(3, 14, 19)
        padded[:, 1:-1, 1:-1] = torch.from_numpy(img).float().permute(2, 0, 1)
        got = Rcas(sharpness)(padded).permute(1, 2, 0).numpy()
        # The 0/0 guard biases ratios by ~1e-5: far below one 8-bit step.
        np.testing.assert_allclose(got, rcas_reference(img, sharpness), atol=1e-4)


# --- invariants --------------------------------------------------------------------------


@pytest.mark.parametrize("make", [TorchEasu, TorchEasuRcas, Lanczos2Upscaler])
@pytest.mark.parametrize("value", [0, 1, 128, 254, 255])
def test_constant_images_stay_exactly_constant(make: Callable[[], Upscaler], value: int) -> None:
    color = np.full((17, 33, 3), value, np.uint8)
    for display in (Size(66, 34), Size(50, 26)):
        out = make().upscale(make_frame(color), display)
        assert torch.isfinite(out).all()
        assert (to_uint8(out) == value).all()
        if make is Lanczos2Upscaler:  # float32 weights sum to 1 within rounding
            assert (out - value / 255.0).abs().max() < 1e-6
        else:  # FSR: de-ringing clamp (EASU), a ring of exact zeros (RCAS)
            assert torch.equal(out, torch.full_like(out, value / 255.0))


@pytest.mark.parametrize("make", [TorchEasu, TorchEasuRcas, Lanczos2Upscaler])
def test_extreme_values_stay_in_range(make: Callable[[], Upscaler]) -> None:
    rng = np.random.default_rng(3)
    color = (rng.integers(0, 2, (24, 40, 3)) * 255).astype(np.uint8)  # only 0 and 255
    color[:, :20] = 0
    for display in (Size(80, 48), Size(68, 41)):
        out = make().upscale(make_frame(color), display)
        assert torch.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
        assert (out[:, :, : display.width // 3] == 0.0).all()  # black stays black


@pytest.mark.parametrize("make", [TorchEasu, TorchEasuRcas, Lanczos2Upscaler])
@pytest.mark.parametrize("render", [Size(64, 36), Size(641, 359)])
@pytest.mark.parametrize("scale", [1.0, 1.5, 1.7, 2.0, 3.0, 4.0])
def test_output_has_display_size(make: Callable[[], Upscaler], render: Size, scale: float) -> None:
    if render.width > 100 and scale > 2.0:
        render = Size(161, 89)  # keep the test fast; odd sizes all the same
    display = render.scaled(scale)
    out = make().upscale(make_frame(random_color(render)), display)
    assert out.shape == (3, display.height, display.width) and out.dtype == torch.float32
    assert torch.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0


def test_easu_at_scale_one_is_nearly_the_input() -> None:
    yy, xx = np.mgrid[0:40, 0:64]
    smooth = 0.5 + 0.3 * np.sin(xx / 6.0)[..., None] * np.cos(yy / 5.0)[..., None] * [1, 0.8, 0.6]
    color = np.round(smooth * 255).astype(np.uint8)
    out = TorchEasu().upscale(make_frame(color), Size(64, 40))
    assert (out - chw(color)).abs().max() <= 2.5 / 255.0


@pytest.mark.parametrize("display", [Size(96, 64), Size(82, 54), Size(48, 32)])
def test_easu_stays_inside_its_source_quad(display: Size) -> None:
    color = random_color(Size(48, 32), seed=4)
    img = chw(color)
    out = TorchEasu().upscale(make_frame(color), display)
    padded = F.pad(img.unsqueeze(0), (0, 1, 0, 1), mode="replicate")[0]
    lo = torch.minimum(torch.minimum(padded[:, :-1, :-1], padded[:, :-1, 1:]),
                       torch.minimum(padded[:, 1:, :-1], padded[:, 1:, 1:]))  # fmt: skip
    hi = torch.maximum(torch.maximum(padded[:, :-1, :-1], padded[:, :-1, 1:]),
                       torch.maximum(padded[:, 1:, :-1], padded[:, 1:, 1:]))  # fmt: skip
    w, h = 48, 32
    fx = np.floor((np.arange(display.width) + 0.5) * w / display.width - 0.5).astype(int)
    fy = np.floor((np.arange(display.height) + 0.5) * h / display.height - 0.5).astype(int)
    # A quad at -1 is the edge texel twice: the same as the quad at 0 of the padded grid.
    ix, iy = torch.from_numpy(np.maximum(fx, 0)), torch.from_numpy(np.maximum(fy, 0))
    lo_o = lo[:, iy][:, :, ix]
    hi_o = hi[:, iy][:, :, ix]
    assert (out >= lo_o - 1e-6).all() and (out <= hi_o + 1e-6).all()


def test_easu_edge_is_steeper_than_bilinear() -> None:
    color = np.full((16, 16, 3), 50, np.uint8)
    color[:, 8:] = 200
    out = TorchEasu().upscale(make_frame(color), Size(32, 32))
    bilinear = F.interpolate(chw(color)[None], size=(32, 32), mode="bilinear", align_corners=False)[
        0
    ]
    easu_step = (out[:, :, 1:] - out[:, :, :-1]).abs().max()
    bilinear_step = (bilinear[:, :, 1:] - bilinear[:, :, :-1]).abs().max()
    assert easu_step > bilinear_step * 1.3


def test_rcas_fewer_stops_sharpen_more_and_stay_in_range() -> None:
    color = random_color(Size(40, 24), seed=5)
    base = TorchEasu().upscale(make_frame(color), Size(80, 48))
    change = []
    for stops in (0.0, 0.2, 0.5, 1.0, 2.0, 4.0):
        out = TorchEasuRcas(sharpness=stops).upscale(make_frame(color), Size(80, 48))
        assert out.min() >= 0.0 and out.max() <= 1.0
        change.append(float((out - base).abs().mean()))
    assert all(a > b for a, b in itertools.pairwise(change)), change
    assert change[0] > 0.005


def test_rcas_denoise_sharpens_less() -> None:
    color = random_color(Size(40, 24), seed=6)
    base = TorchEasu().upscale(make_frame(color), Size(80, 48))
    plain = TorchEasuRcas().upscale(make_frame(color), Size(80, 48))
    quiet = TorchEasuRcas(denoise=True).upscale(make_frame(color), Size(80, 48))
    assert (quiet - base).abs().mean() < (plain - base).abs().mean()
    assert quiet.min() >= 0.0 and quiet.max() <= 1.0


def test_float_input_with_nan_and_inf_gives_finite_output() -> None:
    img = torch.rand(3, 20, 30)
    img[0, 5, 5] = float("nan")
    img[1, 10, 10] = float("inf")
    img[2, 15, 15] = float("-inf")
    out = Easu()(img, (40, 60))
    assert torch.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    padded = torch.zeros(3, 42, 62)
    padded[:, 1:-1, 1:-1] = out
    padded[0, 3, 3] = float("nan")
    sharpened = Rcas()(padded)
    assert torch.isfinite(sharpened).all()


def test_sharpness_must_be_non_negative() -> None:
    with pytest.raises(ValueError, match="sharpness"):
        EasuRcasUpscaler(sharpness=-1.0)


def test_lanczos2_interpolates_smooth_images_like_bicubic() -> None:
    yy, xx = torch.meshgrid(torch.arange(36.0), torch.arange(64.0), indexing="ij")
    smooth = (0.5 + 0.4 * torch.sin(xx / 5) * torch.cos(yy / 7)).expand(3, 36, 64).contiguous()
    out = Lanczos2Upscaler().resample(smooth, (72, 128))
    bicubic = F.interpolate(smooth[None], size=(72, 128), mode="bicubic", align_corners=False)[0]
    assert (out - bicubic)[:, 4:-4, 4:-4].abs().max() < 0.005
    assert torch.equal(Lanczos2Upscaler().resample(smooth, (36, 64)), smooth.clamp(0, 1))


def assert_float16_close(half: torch.Tensor, ref: torch.Tensor) -> None:
    """float16 EASU(+RCAS) against float32: close on average, and off by more than a few
    8-bit steps only on a handful of pixels. Those sit where EASU itself is
    discontinuous (its direction and lobe switches): there float32 EASU moves by as
    much (0.09) when its input moves by 1e-4, float16's rounding of 8-bit values."""
    diff = (half.float().cpu() - ref).abs()
    assert float(diff.mean()) < 0.5 / 255, float(diff.mean())
    assert float((diff > 8 / 255).float().mean()) < 1e-3  # measured: at most 16 of 172,800


def test_float16_matches_float32_but_at_easus_discontinuities() -> None:
    frame = make_frame(random_color(Size(160, 90), seed=7))
    for display in (Size(320, 180), Size(272, 153)):
        ref = TorchEasuRcas().upscale(frame, display)
        half = EasuRcasUpscaler(dtype=torch.float16).upscale(frame, display)
        assert half.dtype == torch.float16
        assert_float16_close(half, ref)
        assert_float16_close(
            EasuUpscaler(dtype=torch.float16).upscale(frame, display),
            TorchEasu().upscale(frame, display),
        )


def test_easu_is_discontinuous_where_float16_differs() -> None:
    """Why the bound above is not a max: a 1e-4 nudge of the float32 input moves float32
    EASU by about as much as float16 does on the same image."""
    frame = make_frame(random_color(Size(160, 90), seed=7))
    display = Size(320, 180)
    ref = TorchEasu().upscale(frame, display)
    half_gap = (EasuUpscaler(dtype=torch.float16).upscale(frame, display).float() - ref).abs()
    image = torch.from_numpy(random_color(Size(160, 90), seed=7)).permute(2, 0, 1).float() / 255
    nudged = image + 1e-4 * torch.randn(image.shape, generator=torch.Generator().manual_seed(1))
    nudge_gap = (Easu()(nudged, (display.height, display.width)) - ref).abs()
    assert float(nudge_gap.max()) > 0.5 * float(half_gap.max()) > 8 / 255


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_float16_matches_cpu() -> None:
    frame = make_frame(random_color(Size(160, 90), seed=7))
    for display in (Size(320, 180), Size(272, 153)):
        cpu = TorchEasuRcas().upscale(frame, display)
        gpu = EasuRcasUpscaler(device="cuda", dtype=torch.float16).upscale(frame, display)
        assert gpu.device.type == "cuda" and gpu.dtype == torch.float16
        assert_float16_close(gpu, cpu)
        easu_gpu = EasuUpscaler(device="cuda", dtype=torch.float16).upscale(frame, display)
        assert_float16_close(easu_gpu, TorchEasu().upscale(frame, display))
        # float32 on CUDA is the CPU's result to rounding.
        gpu32 = EasuRcasUpscaler(device="cuda").upscale(frame, display).cpu()
        assert float((gpu32 - cpu).abs().max()) < 1e-4


@pytest.mark.parametrize("display", [Size(96, 64), Size(82, 54)])
def test_band_size_does_not_change_the_result(display: Size) -> None:
    img = chw(random_color(Size(48, 32), seed=8))
    whole = Easu(band_pixels=1 << 30)(img, (display.height, display.width))
    for band in (1, 500, None):  # one row per band, a few rows, the per-thread default
        got = Easu(band_pixels=band)(img, (display.height, display.width))
        assert torch.equal(got, whole)
        padded = F.pad(got[None], (1, 1, 1, 1))[0]
        sharpened = Rcas(band_pixels=band)(padded.clone())
        assert torch.equal(sharpened, Rcas(band_pixels=1 << 30)(padded.clone()))


@pytest.mark.parametrize("offset", [(0.37, 0.0), (-0.25, 0.0), (0.5, 0.0)])
def test_easu_sample_offset_puts_the_taps_where_the_samples_were_taken(
    offset: tuple[float, float],
) -> None:
    """A smooth edge sampled at i + 0.5 + offset (a jittered render): with the offset
    EASU reconstructs it where it is; without it, the edge moves by the offset."""
    w, h, scale = 32, 8, 2

    def edge(x: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-(x - 15.3) / 1.5))

    def sampled(at: float) -> torch.Tensor:
        row = edge(np.arange(w) + 0.5 + at).astype(np.float32)
        return torch.from_numpy(np.tile(row, (3, h, 1)))

    out_hw = (h * scale, w * scale)
    truth = edge((np.arange(w * scale) + 0.5) / scale)  # at the display pixel centres

    def error(image: torch.Tensor, at: tuple[float, float]) -> float:
        got = Easu(dtype=torch.float32)(image, out_hw, sample_offset=at)[0, h].numpy()
        return float(np.abs(got - truth).max())

    unjittered = error(sampled(0.0), (0.0, 0.0))  # EASU's own error on this edge
    placed = error(sampled(offset[0]), offset)
    ignored = error(sampled(offset[0]), (0.0, 0.0))
    assert placed < 1.5 * unjittered + 1e-3, (placed, unjittered)
    assert ignored > 3 * placed, (ignored, placed)


def test_easu_refuses_an_offset_past_half_a_pixel() -> None:
    with pytest.raises(ValueError, match="sample_offset"):
        Easu()(torch.zeros(3, 4, 4), (8, 8), sample_offset=(0.0, -0.6))
