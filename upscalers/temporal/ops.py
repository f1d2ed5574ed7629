"""Tensor helpers of the temporal upscaler (``upscalers/temporal/upscaler.py``): colour
transforms, 3x3 neighbourhood reductions, sampling grids and sample weights.

All work on (C, H, W) tensors with arithmetic selects (no ``torch.where``, no
boolean indexing): both are slow on the CPU at these sizes.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from server.frames.frame import RenderFrame, Size
from upscalers.fsr1.easu import Easu


def as_tensor(array: Any, device: torch.device) -> torch.Tensor:
    """A tensor on ``device`` from a numpy array (read-only views OK) or a tensor."""
    if isinstance(array, torch.Tensor):
        return array.to(device)
    with warnings.catch_warnings():
        # Ring slots are read-only views; nothing here writes to them.
        warnings.simplefilter("ignore", UserWarning)
        t = torch.from_numpy(np.asarray(array))
    return t.to(device)


def input_device(frame: RenderFrame, default: torch.device) -> torch.device:
    color: Any = frame.color
    return color.device if isinstance(color, torch.Tensor) else default


_RGB_TO_YCOCG = ((0.25, 0.5, 0.25), (0.5, 0.0, -0.5), (-0.25, 0.5, -0.25))


def rgb8_to_ycocg(rgb: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(H, W, 3) uint8 sRGB -> (3, H, W) Y, Co, Cg of the values in [0, 1]: one cast to
    planar float, then the transform and the 1/255 scale as one matrix product."""
    h, w, _ = rgb.shape
    x = rgb.permute(2, 0, 1).to(dtype)
    m = torch.tensor(_RGB_TO_YCOCG, device=rgb.device, dtype=dtype).mul_(1.0 / 255.0)
    return torch.mm(m, x.view(3, -1)).view(3, h, w)


def pad1(x: torch.Tensor) -> torch.Tensor:
    """(C, H, W) -> (C, H + 2, W + 2), edges replicated."""
    return F.pad(x.unsqueeze(0), (1, 1, 1, 1), mode="replicate")[0]


def box_3x3(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel min and max over the 3x3 neighbourhood of a (C, H, W) tensor."""
    p = pad1(x)
    left, mid, right = p[..., :-2], p[..., 1:-1], p[..., 2:]
    lo = torch.minimum(torch.minimum(left, mid), right)
    hi = torch.maximum(torch.maximum(left, mid), right)
    lo = torch.minimum(torch.minimum(lo[:, :-2], lo[:, 1:-1]), lo[:, 2:])
    hi = torch.maximum(torch.maximum(hi[:, :-2], hi[:, 1:-1]), hi[:, 2:])
    return lo, hi


def render_range_at_display(
    color: torch.Tensor, big_h: int, big_w: int, slack: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """The output clamp's bounds: per display pixel, the min and max of the 3x3
    neighbourhood of its render pixel (nearest) in ``color`` (C, h, w), widened by
    ``slack`` (levels of ``color``) each way."""
    lo, hi = box_3x3(color)
    if slack:
        lo, hi = lo - slack, hi + slack
    iy = nearest_index(big_h, color.shape[1], color.device)
    ix = nearest_index(big_w, color.shape[2], color.device)
    return (
        lo.index_select(1, iy).index_select(2, ix),
        hi.index_select(1, iy).index_select(2, ix),
    )


def axis_scale(render: Size, display: Size) -> float:
    """Display over render pixels on the larger axis: the upscaling factor."""
    return max(display.width / render.width, display.height / render.height)


def widen_box(
    lo: torch.Tensor, hi: torch.Tensor, slack: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The box [lo, hi] widened by ``slack`` times its extent on each side (in place);
    the numba path's ``render_finish`` computes the same in the same order."""
    if slack == 0.0:
        return lo, hi
    d = (hi - lo).mul_(slack)
    return lo.sub_(d), hi.add_(d)


def closest_3x3(depth: torch.Tensor, carry: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel, the smallest depth of the 3x3 neighbourhood of the (H, W) depth and the
    ``carry`` (C, H, W) values that go with it (separable: row then column), with
    arithmetic selects (no torch.where)."""
    d = pad1(depth.unsqueeze(0))
    c = pad1(carry)
    best_d, best_c = d[..., 1:-1], c[..., 1:-1]
    for sl in (slice(0, -2), slice(2, None)):
        cand = d[..., sl]
        closer = (cand < best_d).to(depth.dtype)
        best_d = torch.minimum(best_d, cand)
        best_c = torch.lerp(best_c, c[..., sl], closer)
    d, c = best_d, best_c
    best_d, best_c = d[:, 1:-1], c[:, 1:-1]
    for sl in (slice(0, -2), slice(2, None)):
        cand = d[:, sl]
        closer = (cand < best_d).to(depth.dtype)
        best_d = torch.minimum(best_d, cand)
        best_c = torch.lerp(best_c, c[:, sl], closer)
    return best_d[0], best_c


def sharpen(x: torch.Tensor, amount: float) -> torch.Tensor:
    """x + amount * (x - mean of the 4 edge neighbours), edges replicated, (C, H, W)."""
    pad = pad1(x)
    nb = pad[:, :-2, 1:-1] + pad[:, 2:, 1:-1] + pad[:, 1:-1, :-2] + pad[:, 1:-1, 2:]
    return nb.mul_(-0.25 * amount).add_(x, alpha=1.0 + amount)


def max_2x2(x: torch.Tensor) -> torch.Tensor:
    """out[j, i] = max of x over [j, j + 1] x [i, i + 1] (edges replicated)."""
    h, w = x.shape
    if w > 1:
        x = torch.maximum(x, torch.cat((x[:, 1:], x[:, w - 1 :]), 1))
    if h > 1:
        x = torch.maximum(x, torch.cat((x[1:], x[h - 1 :]), 0))
    return x


def jitter(frame: RenderFrame) -> tuple[float, float]:
    jx, jy = frame.meta.jitter
    jx = float(jx) if math.isfinite(jx) else 0.0
    jy = float(jy) if math.isfinite(jy) else 0.0
    return min(max(jx, -0.5), 0.5), min(max(jy, -0.5), 0.5)


def near_far(frame: RenderFrame) -> tuple[float, float] | None:
    near, far = float(frame.meta.camera.near), float(frame.meta.camera.far)
    if math.isfinite(near) and math.isfinite(far) and 0.0 < near < far:
        return near, far
    return None


def pixel_grid(display: Size, scale: int, dev: torch.device, dt: torch.dtype) -> torch.Tensor:
    """(S, S, h, w, 2) normalized grid_sample coordinates of the display pixel centres in
    planar layout (see ``reconstruct_blocked``; S = 1 is the plain (1, 1, H, W, 2))."""
    big_w, big_h = display
    gx = torch.arange(big_w, device=dev, dtype=dt).add_(0.5).mul_(2.0 / big_w).sub_(1.0)
    gy = torch.arange(big_h, device=dev, dtype=dt).add_(0.5).mul_(2.0 / big_h).sub_(1.0)
    grid = torch.stack((gx.expand(big_h, big_w), gy.unsqueeze(1).expand(big_h, big_w)), -1)
    return to_planar(grid.permute(2, 0, 1), scale).permute(1, 2, 3, 4, 0).contiguous()


def to_planar(x: torch.Tensor, scale: int) -> torch.Tensor:
    """(C, H, W) standard layout -> (C, S, S, H/S, W/S) planar view (no copy)."""
    c, big_h, big_w = x.shape
    return x.view(c, big_h // scale, scale, big_w // scale, scale).permute(0, 2, 4, 1, 3)


def sharpen_fraction(u: torch.Tensor, k: float) -> torch.Tensor:
    """Positions u (grid_sample pixel units) with the fraction between the two bracketing
    sample centres pushed towards the nearer one by factor k."""
    if k == 1.0:
        return u
    base = (u - 0.5).floor_()
    frac = (u - 0.5 - base).sub_(0.5).mul_(k).clamp_(-0.5, 0.5).add_(0.5)
    return base.add_(0.5).add_(frac)


def jittered_grid(
    display: Size,
    render: Size,
    jitter: tuple[float, float],
    k: float,
    dev: torch.device,
    dt: torch.dtype,
) -> torch.Tensor:
    """Grid that samples the render image at the display pixel centres, with render
    pixel i taken to sit at i + 0.5 + jitter (so grid_sample's i + 0.5 is shifted)."""
    big_w, big_h = display
    w, h = render
    gx = torch.arange(big_w, device=dev, dtype=dt).add_(0.5).mul_(w / big_w).sub_(jitter[0])
    gy = torch.arange(big_h, device=dev, dtype=dt).add_(0.5).mul_(h / big_h).sub_(jitter[1])
    gx, gy = sharpen_fraction(gx, k), sharpen_fraction(gy, k)
    gx = gx.mul_(2.0 / w).sub_(1.0)
    gy = gy.mul_(2.0 / h).sub_(1.0)
    return torch.stack((gx.expand(big_h, big_w), gy.unsqueeze(1).expand(big_h, big_w)), -1)[None]


def axis_weight(
    n: int, n_display: int, n_render: int, j: float, sigma: float, dev: torch.device,
    dt: torch.dtype,
) -> torch.Tensor:  # fmt: skip
    """Gaussian of the distance (display pixels) from each of the first ``n`` display
    pixel centres to the nearest render sample along one axis (jitter ``j``)."""
    s = n_display / n_render
    u = torch.arange(n, device=dev, dtype=dt).add_(0.5).mul_(1.0 / s).sub_(0.5 + j)
    d = (u - u.round()).mul_(s)
    return d.square_().mul_(-0.5 / (sigma * sigma)).exp_()


def phase_taps(scale: int, j: float, k: float) -> list[tuple[int, float]]:
    """For an integer scale, display sub-pixel b of render pixel i lies between samples
    i + n_b and i + n_b + 1 at fraction f_b (sharpened by k): the (n_b, f_b) per b."""
    taps = []
    for b in range(scale):
        c = (b + 0.5) / scale - 0.5 - j
        n = math.floor(c)
        f = min(max((c - n - 0.5) * k, -0.5), 0.5) + 0.5
        taps.append((n, f))
    return taps


def reconstruct_blocked(
    x: torch.Tensor, scale: int, jitter: tuple[float, float], k: float, out: torch.Tensor
) -> torch.Tensor:
    """Bilinear reconstruction of the jittered (C, h, w) samples at the display pixel
    centres for an integer scale S, into ``out`` in planar layout (C, S, S, h, w)
    (display pixel (i S + a, j S + b) at [:, a, b, i, j]): the jitter is uniform, so
    each sub-pixel phase is a lerp of whole shifted render images."""
    c, h, w = x.shape
    # Tap offsets n are -1 or 0 (the jitter is within half a pixel): one replicated
    # border is enough, shifts are slices.
    xp = pad1(x)[:, 1:-1]
    horiz = torch.empty((scale, c, h + 2, w), device=x.device, dtype=x.dtype)
    for b, (n, f) in enumerate(phase_taps(scale, jitter[0], k)):
        torch.lerp(xp[..., 1 + n : 1 + n + w], xp[..., 2 + n : 2 + n + w], f, out=horiz[b, :, 1:-1])
    horiz[:, :, 0] = horiz[:, :, 1]
    horiz[:, :, -1] = horiz[:, :, -2]
    for a, (n, f) in enumerate(phase_taps(scale, jitter[1], k)):
        top, bottom = horiz[:, :, 1 + n : 1 + n + h], horiz[:, :, 2 + n : 2 + n + h]
        torch.lerp(top, bottom, f, out=out[:, a].transpose(0, 1))
    return out


def nearest_index(n_display: int, n_render: int, dev: torch.device) -> torch.Tensor:
    """Index of the render pixel whose area holds each display pixel centre."""
    i = torch.arange(n_display, device=dev, dtype=torch.float64).add_(0.5)
    return i.mul_(n_render / n_display).floor_().clamp_(0, n_render - 1).long()


def neighbour_sum_planar(x: torch.Tensor, axis: int, out: torch.Tensor) -> torch.Tensor:
    """x[p - 1] + x[p + 1] along display rows (axis 0) or columns (axis 1) of a planar
    (S, S, h, w) plane (see ``reconstruct_blocked``; S >= 2), edges replicated, into
    ``out``. Sub-pixel b's neighbours are sub-pixels b - 1 and b + 1 of the same render
    pixel, or of the render pixel before / after at the block edges."""
    sub, blk = axis, axis + 2
    s, n = x.shape[sub], x.shape[blk]
    blk -= 1  # index of the block dimension once ``sub`` is selected away
    for b in range(s):
        o = out.select(sub, b)
        if 0 < b < s - 1:
            torch.add(x.select(sub, b - 1), x.select(sub, b + 1), out=o)
            continue
        if b == 0:
            left, right = x.select(sub, s - 1), x.select(sub, 1)
            torch.add(
                left.narrow(blk, 0, n - 1), right.narrow(blk, 1, n - 1), out=o.narrow(blk, 1, n - 1)
            )
            edge = x.select(sub, 0).narrow(blk, 0, 1)
            torch.add(edge, right.narrow(blk, 0, 1), out=o.narrow(blk, 0, 1))
        if b == s - 1:
            left, right = x.select(sub, s - 2), x.select(sub, 0)
            torch.add(
                left.narrow(blk, 0, n - 1), right.narrow(blk, 1, n - 1), out=o.narrow(blk, 0, n - 1)
            )
            edge = x.select(sub, s - 1).narrow(blk, n - 1, 1)
            torch.add(left.narrow(blk, n - 1, 1), edge, out=o.narrow(blk, n - 1, 1))
    return out


_YCOCG_TO_RGB = ((1.0, 1.0, -1.0), (1.0, 0.0, 1.0), (1.0, -1.0, -1.0))


def ycocg_to_rgb8(ycocg: torch.Tensor) -> torch.Tensor:
    """(3, H, W) YCoCg of sRGB values in [0, 1] -> (3, H, W) uint8 sRGB, rounded half up
    and clamped: the conversion, the scale to 255 and the rounding offset are one
    matrix product. The result is a view of an (H, W, 3) buffer, the ring U layout, so
    copying it into a slot is a plain memcpy; the interleave happens here, one channel
    at a time (a strided cast is several times cheaper than a general transpose)."""
    _, big_h, big_w = ycocg.shape
    dev, dt = ycocg.device, ycocg.dtype
    m = torch.tensor(_YCOCG_TO_RGB, device=dev, dtype=dt).mul_(255.0)
    half = torch.full((3, 1), 0.5, device=dev, dtype=dt)
    rgb = torch.addmm(half, m, ycocg.reshape(3, -1)).clamp_(0.0, 255.0)
    out = torch.empty((big_h * big_w, 3), device=dev, dtype=torch.uint8)
    for c in range(3):
        out[:, c].copy_(rgb[c])
    return out.view(big_h, big_w, 3).permute(2, 0, 1)


def spatial_reconstruction(
    color: torch.Tensor, display: Size, jit: tuple[float, float], easu: Easu
) -> torch.Tensor:
    """(h, w, 3) uint8 sRGB samples taken at (i + 0.5 + jitter) -> (3, H, W) YCoCg (of
    values in [0, 1], as ``rgb8_to_ycocg``): FSR 1's EASU of them, its taps where the
    samples were taken (``sample_offset``).

    What a reset starts the history from. Against the Lanczos-2 it replaces, on the
    training photographs at 2x: the three frames after a cut +0.3 dB each. EASU's own
    de-ringing clamp keeps it inside each quad's range."""
    rgb = color.permute(2, 0, 1).to(torch.float32).mul_(1.0 / 255.0)
    up = easu(rgb, (display.height, display.width), sample_offset=jit)
    to_ycocg = torch.tensor(_RGB_TO_YCOCG, device=up.device, dtype=up.dtype)
    return torch.mm(to_ycocg, up.reshape(3, -1)).view(3, display.height, display.width)
