"""Network input built from the frame contract and the upscaler's own previous output.

Everything is at render size (h, w) for an integer scale s, so the network never
touches a display-size tensor except through ``pixel_unshuffle``-ordered planes:

| channels | what | why |
|---|---|---|
| 0-2 | colour, sRGB / 255 | the samples themselves |
| 3 | log linear depth, 0 at near .. 1 at far (sky) | edges and disocclusion |
| 4-5 | motion / 8 render px, clamped to +-4 | how far history moved |
| 6-7 | jitter x 2, constant planes | where this frame's samples sit |
| 8 | history valid: history exists and reprojects inside the screen | first frame, borders |
| 9 | depth change: this depth minus last frame's depth at the reprojected spot | disocclusion |
| 10.. | previous output warped by motion, 3 s s planes (pixel_unshuffle order) | accumulation |

Warping fetches the (1, 3, H, W) previous output at every display pixel's
position plus its render pixel's motion times s, batched over the s s sub-pixel
phases as the temporal upscaler does (the CPU grid_sample kernel splits its
work over the batch), so the result is already in pixel_unshuffle order.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from upscalers.names import DEFAULT_NETWORK_BASE, check_network_base

SCALE = 2
# Input channels of a network trained for ``SCALE``.
BASE_CHANNELS = 10
MOTION_UNIT = 8.0
MOTION_LIMIT = 4.0
DEPTH_CHANGE_GAIN = 8.0
JITTER_CHANNELS = slice(6, 8)


def feature_channels(scale: int = SCALE) -> int:
    return BASE_CHANNELS + 3 * scale * scale


@dataclass
class FrameTensors:
    """A batch of N frames as (N, C, h, w) tensors on the compute device (N = 1 when
    upscaling; the training batches crops)."""

    color: torch.Tensor  # (N, 3, h, w) sRGB in [0, 1]
    depth: torch.Tensor  # (N, 1, h, w) NDC z in [0, 1]
    motion: torch.Tensor  # (N, 2, h, w) render pixels, current -> previous
    jitter: torch.Tensor  # (N, 2) render pixels, x then y
    near_far: torch.Tensor | None  # (N, 2) camera near and far; None: depth used as is


@dataclass
class History:
    """What the next frame reuses: the last output and the depth feature it was made with."""

    output: torch.Tensor  # (N, 3, H, W)
    depth_feature: torch.Tensor  # (N, 1, h, w)


def depth_feature(depth: torch.Tensor, near_far: torch.Tensor | None) -> torch.Tensor:
    """(N, 1, h, w) NDC z -> log(linear depth / near) / log(far / near) in [0, 1]."""
    z = torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    if near_far is None:
        return z
    near = near_far[:, 0].view(-1, 1, 1, 1).to(z.dtype)
    far = near_far[:, 1].view(-1, 1, 1, 1).to(z.dtype)
    lin = (near * far) / (far - z * (far - near)).clamp(min=1e-6)
    return lin.div(near).clamp(min=1.0).log().div((far / near).log()).clamp(0.0, 1.0)


def _phase_grid(
    h: int, w: int, scale: int, motion: torch.Tensor, dtype: torch.dtype
) -> torch.Tensor:
    """(N s s, h, w, 2) grid_sample coordinates: display sub-pixel (a, b) of render
    pixel (i, j) at its centre moved by the render pixel's motion (N, 2, h, w)."""
    dev = motion.device
    n = motion.shape[0]
    sub = (torch.arange(scale, device=dev, dtype=dtype) + 0.5) / scale  # in render px
    xs = torch.arange(w, device=dev, dtype=dtype)
    ys = torch.arange(h, device=dev, dtype=dtype)
    # Display-pixel centres in render pixel units, per phase: (s, w) and (s, h).
    px = xs.unsqueeze(0) + sub.unsqueeze(1)
    py = ys.unsqueeze(0) + sub.unsqueeze(1)
    mx = motion[:, 0].to(dtype)[:, None, None]  # (N, 1, 1, h, w)
    my = motion[:, 1].to(dtype)[:, None, None]
    # normalized: x_n = 2 x / w - 1 with x in render px (same as display px / W).
    gx = (px[None, None, :, None, :] + mx).mul(2.0 / w).sub(1.0)  # (N, 1, s, h, w)
    gy = (py[None, :, None, :, None] + my).mul(2.0 / h).sub(1.0)  # (N, s, 1, h, w)
    gx = gx.expand(n, scale, scale, h, w)
    gy = gy.expand(n, scale, scale, h, w)
    return torch.stack((gx, gy), -1).reshape(n * scale * scale, h, w, 2)


def warp_history(output: torch.Tensor, motion: torch.Tensor, scale: int) -> torch.Tensor:
    """(N, 3, H, W) previous output fetched at p + motion -> (N, 3 s s, h, w) in
    pixel_unshuffle order (channel c s s + a s + b is display pixel (i s + a, j s + b))."""
    b, _, h, w = motion.shape
    n = scale * scale
    grid = _phase_grid(h, w, scale, motion, torch.float32)
    src = output.to(torch.float32).unsqueeze(1).expand(b, n, *output.shape[1:])
    src = src.reshape(b * n, *output.shape[1:])  # a view when b == 1
    fetched = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)
    # (b n, 3, h, w) -> (b, 3 n, h, w), channel = c n + phase
    fetched = fetched.view(b, n, 3, h, w).transpose(1, 2)
    return fetched.reshape(b, 3 * n, h, w).to(output.dtype)


def _reprojected_inside(motion: torch.Tensor) -> torch.Tensor:
    """(N, 1, h, w) 1 where the pixel centre plus motion stays on the screen."""
    _, _, h, w = motion.shape
    dev, dt = motion.device, motion.dtype
    qx = motion[:, 0:1] + torch.arange(w, device=dev, dtype=dt).add_(0.5)
    qy = motion[:, 1:2] + torch.arange(h, device=dev, dtype=dt).add_(0.5).unsqueeze(1)
    return ((qx >= 0.0) & (qx <= w) & (qy >= 0.0) & (qy <= h)).to(dt)


def _warp_render_plane(plane: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """(N, C, h, w) render-size plane of the previous frame fetched at p + motion."""
    _, _, h, w = motion.shape
    grid = _phase_grid(h, w, 1, motion, plane.dtype)
    return F.grid_sample(plane, grid, mode="nearest", padding_mode="border", align_corners=False)


# The upsampling a network's residual is added to: "bilinear" (the weights before
# 2026-11-27) or "cubic" (Catmull-Rom). Renders are box averages of the scene over
# their footprints; bilinear interpolation blurs them a second time, and a residual on
# it spent its capacity undoing that (on photographs' first frames a bilinear base was
# 1.5 dB below bicubic, and the trained U-Net 0.2 dB below bicubic still).
# Kernel radius of each base (upscalers.names.NETWORK_BASES): samples at offsets -r..r
# can be weighted for |d| < 1.
BASE_RADIUS = {"bilinear": 1, "cubic": 2}


def _tap_weights(d: torch.Tensor, base: str) -> torch.Tensor:
    """Weights of the samples at offsets -r..r (``BASE_RADIUS``) for a position d
    (|d| < 1) after the sample at offset 0: (..., 2 r + 1), summing to one."""
    r = BASE_RADIUS[check_network_base(base)]
    k = torch.arange(-r, r + 1, device=d.device, dtype=d.dtype)
    t = (d.unsqueeze(-1) - k).abs()
    if base == "bilinear":
        return F.relu(1.0 - t)
    # Keys' cubic with a = -0.5 (Catmull-Rom): interpolating, support 2.
    near = (1.5 * t - 2.5) * t * t + 1.0
    far = ((-0.5 * t + 2.5) * t - 4.0) * t + 2.0
    return torch.where(t <= 1.0, near, torch.where(t < 2.0, far, torch.zeros_like(t)))


def base_phases(
    color: torch.Tensor,
    scale: int,
    jitter: torch.Tensor | None = None,
    base: str = DEFAULT_NETWORK_BASE,
) -> torch.Tensor:
    """(N, 3, h, w) -> (N, 3 s s, h, w): the upsampling ``base`` (edges clamped) in
    pixel_unshuffle order, as one grouped convolution at render size (3x3 bilinear, 5x5
    cubic) instead of a
    display-size pass. With ``jitter`` (N, 2), render pixel i is taken to sit at
    i + 0.5 + j, where this frame sampled it, so the result is aligned with the
    unjittered display grid whatever the jitter (a shifted base would leave the
    network a sub-pixel shift to undo)."""
    n = color.shape[0]
    dev = color.device
    # Display sub-pixel a of render pixel i lies at render coordinate i + (a + 0.5) / s;
    # its offset from sample i is d = (a + 0.5) / s - 0.5 - j, |d| < 1.
    sub = (torch.arange(scale, device=dev, dtype=torch.float32) + 0.5) / scale - 0.5
    j = torch.zeros((n, 2), device=dev) if jitter is None else jitter.to(dev, torch.float32)
    d = sub.view(1, 1, scale) - j.view(n, 2, 1)  # (N, axis, s)
    taps = _tap_weights(d, base)  # (N, axis, s, 2 r + 1)
    r, size = BASE_RADIUS[base], taps.shape[-1]
    tx, ty = taps[:, 0], taps[:, 1]
    kernel = torch.einsum("nay,nbx->nabyx", ty, tx).reshape(n, 1, scale * scale, size, size)
    weight = kernel.expand(n, 3, scale * scale, size, size).reshape(-1, 1, size, size)
    _, c, h, w = color.shape
    padded = F.pad(color, (r, r, r, r), mode="replicate").reshape(1, n * c, h + 2 * r, w + 2 * r)
    out = F.conv2d(padded, weight.to(color.dtype), groups=n * c)
    return out.view(n, c * scale * scale, h, w)


def bilinear_phases(
    color: torch.Tensor, scale: int, jitter: torch.Tensor | None = None
) -> torch.Tensor:
    """``base_phases`` with the bilinear base: the network's input in place of a
    missing history."""
    return base_phases(color, scale, jitter, "bilinear")


def jitter_of(features: torch.Tensor) -> torch.Tensor:
    """(N, 2) jitter in render pixels, read back from the feature planes."""
    return features[:, JITTER_CHANNELS, 0, 0].float() / 2.0


def build_features(
    frame: FrameTensors, history: History | None, scale: int = SCALE
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, C, h, w) network input and this frame's depth feature (kept for the next)."""
    color = frame.color
    b, _, h, w = color.shape
    dt = color.dtype
    dfeat = depth_feature(frame.depth.float(), frame.near_far).to(dt)
    motion = frame.motion.float()
    motion = torch.nan_to_num(motion, nan=0.0, posinf=0.0, neginf=0.0)
    lim = 4.0 * max(h, w)
    motion = motion.clamp(-lim, lim)
    motion_feat = motion.div(MOTION_UNIT).clamp(-MOTION_LIMIT, MOTION_LIMIT).to(dt)
    jitter = torch.nan_to_num(frame.jitter.to(color.device, dt)).clamp(-0.5, 0.5)
    jit = jitter.mul(2.0).view(b, 2, 1, 1).expand(b, 2, h, w)
    usable = (
        history is not None
        and history.output.shape == (b, 3, h * scale, w * scale)
        and history.depth_feature.shape == (b, 1, h, w)
    )
    if usable:
        assert history is not None
        valid = _reprojected_inside(motion).to(dt)
        warped = warp_history(history.output, motion, scale).to(dt)
        prev_depth = _warp_render_plane(history.depth_feature.float(), motion).to(dt)
        change = (dfeat - prev_depth).mul(DEPTH_CHANGE_GAIN).clamp(-1.0, 1.0).mul(valid)
    else:
        valid = torch.zeros((b, 1, h, w), device=color.device, dtype=dt)
        warped = bilinear_phases(color, scale, jitter)
        change = torch.zeros_like(valid)
    x = torch.cat((color, dfeat, motion_feat, jit, valid, change, warped), 1)
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0), dfeat
