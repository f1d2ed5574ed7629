"""Texture sampling, lighting, sky, fog and the sRGB encode.

Textures are sampled once per hit pixel, after visibility is resolved: bilinear
within one mip level chosen per pixel (level = round(lod)), four gathers per
channel from the atlas' channel planes. Cheaper than trilinear and enough to
stop distant texture shimmer; materials with mip off alias on purpose.

Colour is kept as three float32 planes (channel-first) until the final encode:
per-channel blends of planes are plain elementwise ops, where (n, 3) * (n, 1)
broadcasts are a slow path on CPU.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch

from server.game.render.rays import RayGrid
from server.game.render.scene import Lighting
from server.game.render.surfaces import FOOT, LAM, NY, TEX, TINT, GroundSurface, S, U, V
from server.game.render.textures import LEVEL_OFFSETS, LEVELS, PYRAMID_TEXELS, SIZE, TextureAtlas

LOG2_SIZE = SIZE.bit_length() - 1
# The sRGB encode is a table lookup on the linear value quantized to this many steps.
SRGB_LUT_STEPS = 1 << 14


def mip_level(foot: torch.Tensor) -> torch.Tensor:
    """int32 floor(log2(foot)) clamped to the pyramid, from the float's exponent bits.

    ``foot`` already carries 2^(lod_bias + 0.5), so this is round(lod); 0, NaN
    and negative values give level 0, inf the last level.
    """
    bits = foot.view(torch.int32)
    level = torch.bitwise_right_shift(bits, 23).sub_(127)
    # Negative floats have the sign bit set: their shifted exponent is < -127.
    return level.clamp_(0, LEVELS - 1)


def _pow2(exponent: torch.Tensor) -> torch.Tensor:
    """2.0 ** exponent (int32, in the normal float range), exactly, as float32."""
    return torch.bitwise_left_shift(exponent + 127, 23).view(torch.float32)


@cache
def _level_offsets(device: str) -> torch.Tensor:
    """(LEVELS,) int32 texel offset of each mip level inside a pyramid."""
    return torch.tensor(LEVEL_OFFSETS, dtype=torch.int32, device=device)


def sample_texture(
    atlas: TextureAtlas, u: torch.Tensor, v: torch.Tensor, tex: torch.Tensor, foot: torch.Tensor
) -> list[torch.Tensor]:
    """Three planes of linear albedo: bilinear, repeat wrap, per-pixel mip level.

    Integer texel coordinates wrap with ``& (size - 1)`` (sizes are powers of two,
    and two's complement makes that a floor-modulo for negative coordinates too);
    each row of the 2x2 footprint is one gather of a texel pair per channel.
    """
    shape = u.shape
    u, v, tex, foot = (a.reshape(-1) for a in (u, v, tex, foot))
    level = mip_level(foot)
    shift = torch.neg(level).add_(LOG2_SIZE)  # log2 of the level's size
    size = _pow2(shift)
    mask = torch.ones_like(shift).bitwise_left_shift_(shift).sub_(1)

    def axis(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = c * size
        x.sub_(0.5)
        x0 = x.floor()
        frac = x.sub_(x0)
        return x0.to(torch.int32).bitwise_and_(mask), frac

    x0, fx = axis(u)
    y0, fy = axis(v)
    base = _level_offsets(str(u.device)).index_select(0, level)
    base.add_(tex.to(torch.int32).mul_(PYRAMID_TEXELS)).add_(x0)
    y1 = (y0 + 1).bitwise_and_(mask).bitwise_left_shift_(shift).add_(base)
    y0.bitwise_left_shift_(shift).add_(base)
    out = []
    for pairs in atlas.pairs:
        top = pairs.index_select(0, y0).view(torch.float32).view(-1, 2)
        bottom = pairs.index_select(0, y1).view(torch.float32).view(-1, 2)
        row0 = torch.lerp(top[:, 0], top[:, 1], fx)
        row1 = torch.lerp(bottom[:, 0], bottom[:, 1], fx)
        out.append(row0.lerp_(row1, fy).view(shape))
    return out


def _light_terms(lighting: Lighting) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel: light = a + b * n_y + c * max(n . sun, 0)."""
    sky_amb = np.asarray(lighting.sky_ambient)
    ground_amb = np.asarray(lighting.ground_ambient)
    half = 0.5 * (sky_amb - ground_amb)
    return ground_amb + half, half, np.asarray(lighting.sun_color)


def _fog(s: torch.Tensor, far: float) -> torch.Tensor:
    """(t / far)^2 clamped to [0, 1], from s = 1 / t (fog reaches the horizon at far)."""
    fog = (s * far).reciprocal_().clamp_(0.0, 1.0)
    return fog.mul_(fog)


def shade(
    atlas: TextureAtlas, surf: torch.Tensor, lighting: Lighting, far: float, s: torch.Tensor
) -> list[torch.Tensor]:
    """Three planes of linear colour: Lambert sun + hemisphere ambient, then distance fog.

    ``surf`` holds the surface rows of surfaces.py (any trailing shape).
    """
    albedo = sample_texture(atlas, surf[U], surf[V], surf[TEX], surf[FOOT])
    a, b, c = _light_terms(lighting)
    fog = _fog(s, far)
    keep = 1.0 - fog
    out = []
    for ch in range(3):
        light = surf[NY] * float(b[ch])
        light.add_(float(a[ch])).add_(surf[LAM], alpha=float(c[ch]))
        col = albedo[ch].mul_(surf[TINT + ch]).mul_(light).mul_(keep)
        out.append(col.add_(fog, alpha=float(lighting.horizon[ch])))
    return out


def shade_ground(
    atlas: TextureAtlas, g: GroundSurface, lighting: Lighting, far: float
) -> list[torch.Tensor]:
    """Like ``shade`` with the ground's constant normal: light is one number per channel."""
    rows = g.rows
    albedo = sample_texture(atlas, rows[U], rows[V], rows[TEX], rows[FOOT])
    a, b, c = _light_terms(lighting)
    fog = _fog(rows[S].clamp_min(1.0 / far), far)
    keep = 1.0 - fog
    out = []
    for ch in range(3):
        light = float(a[ch] + b[ch] * g.ny + c[ch] * g.lam)
        col = albedo[ch].mul_(rows[TINT + ch]).mul_(keep).mul_(light)
        out.append(col.add_(fog, alpha=float(lighting.horizon[ch])))
    return out


def sky_into(out: torch.Tensor, grid: RayGrid, lighting: Lighting, r0: int, r1: int) -> None:
    """Linear sky of band rows [r0, r1) into ``out`` (3, r1 - r0, width): by elevation."""
    ys = grid.ys[r0:r1]
    dy = grid.field((float(grid.c0[1]), float(grid.cx[1]), float(grid.cy[1])), grid.xs, ys)
    row, col = grid.norm2_terms()
    k = (row[r0:r1, None] + col[None, :]).rsqrt_().mul_(dy)
    k.clamp_(0.0, 1.0).sqrt_()
    for ch in range(3):
        h, z = lighting.horizon[ch], lighting.zenith[ch]
        torch.mul(k, z - h, out=out[ch]).add_(h)


def sky(grid: RayGrid, lighting: Lighting) -> torch.Tensor:
    """(rows, width, 3) linear sky: horizon to zenith by the ray's elevation."""
    out = torch.empty(3, grid.rows, grid.width, device=grid.xs.device)
    sky_into(out, grid, lighting, 0, grid.rows)
    return out.permute(1, 2, 0)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Clamp tonemap then the sRGB transfer curve, in [0, 1]."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.pow(1.0 / 2.4) - 0.055)


def quantize_into(srgb: torch.Tensor, out: torch.Tensor) -> None:
    """Write [0, 1] floats as uint8 into ``out``; NaN becomes 0 instead of garbage."""
    q = torch.nan_to_num(srgb, nan=0.0, posinf=1.0, neginf=0.0).mul_(255.0).round_().clamp_(0, 255)
    out.copy_(q)


@cache
def srgb_lut(device: str) -> torch.Tensor:
    """uint8 sRGB of the linear values i / (SRGB_LUT_STEPS - 1)."""
    lin = torch.arange(SRGB_LUT_STEPS, dtype=torch.float64) / (SRGB_LUT_STEPS - 1)
    lut = torch.empty(SRGB_LUT_STEPS, dtype=torch.uint8)
    quantize_into(linear_to_srgb(lin), lut)
    return lut.to(device)


def encode_srgb_into(planes: torch.Tensor, out: torch.Tensor) -> None:
    """Linear (3, H, W) planes -> uint8 sRGB (H, W, 3) ``out``: clamp (NaN -> 0), table lookup.

    Same as ``quantize_into(linear_to_srgb(.))`` up to the table's resolution
    (rarely 1 code off), at a fraction of the cost of ``pow``.
    """
    h, w = planes.shape[1:]
    idx = torch.empty(h, w, 3, dtype=torch.int32, device=planes.device)
    scaled = torch.empty(h, w, device=planes.device)
    for ch in range(3):
        torch.clamp(planes[ch], 0.0, 1.0, out=scaled)
        scaled.mul_(SRGB_LUT_STEPS - 1).add_(0.5)
        idx[..., ch].copy_(scaled)
    # NaN survives the float clamp and converts to an out-of-range integer (INT_MIN
    # on x86, 0 on ARM): clamping the index sends it to 0 like ``quantize_into``.
    idx.clamp_(0, SRGB_LUT_STEPS - 1)
    lut = srgb_lut(str(planes.device))
    torch.index_select(lut, 0, idx.view(-1), out=out.view(-1))
