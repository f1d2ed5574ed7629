"""Texture sampling, lighting, sky, fog and the sRGB encode.

Textures are sampled once per hit pixel, after visibility is resolved: bilinear
within one mip level chosen per pixel (level = round(lod)), four gathers from
the flat atlas. Cheaper than trilinear and enough to stop distant texture
shimmer; materials with mip off alias on purpose.
"""

from __future__ import annotations

import torch

from server.render.rays import RayGrid
from server.render.scene import Lighting
from server.render.surfaces import Surface
from server.render.textures import LEVELS, PYRAMID_TEXELS, TextureAtlas


def sample_texture(atlas: TextureAtlas, s: Surface) -> torch.Tensor:
    """(n, 3) linear albedo: bilinear, repeat wrap, per-pixel mip level."""
    level = s.lod.round().clamp_(0, LEVELS - 1).long()
    size = atlas.level_sizes[level]
    base = s.texture * PYRAMID_TEXELS + atlas.level_offsets[level]
    x = s.u * size - 0.5
    y = s.v * size - 0.5
    x0 = x.floor()
    y0 = y.floor()
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    # Wrap with floor-division so negative coordinates repeat too.
    x0 = x0 - size * (x0 / size).floor()
    y0 = y0 - size * (y0 / size).floor()
    x1 = x0 + 1.0
    x1 = x1 - size * (x1 >= size).float()
    y1 = y0 + 1.0
    y1 = y1 - size * (y1 >= size).float()
    row0 = base + y0 * size
    row1 = base + y1 * size
    packed = atlas.packed
    n = s.u.shape[0]

    def tap(row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        return packed.take((row + col).long()).view(torch.float16).view(n, 4).float()

    # Explicit a + (b - a) w: torch.lerp with a broadcast weight is a slow path.
    top = tap(row0, x0)
    top += (tap(row0, x1) - top) * fx
    bottom = tap(row1, x0)
    bottom += (tap(row1, x1) - bottom) * fx
    top += (bottom - top) * fy
    return top[:, :3]


def shade(atlas: TextureAtlas, s: Surface, lighting: Lighting, far: float) -> torch.Tensor:
    """(n, 3) linear colour: Lambert sun + hemisphere ambient, then distance fog."""
    device = s.t.device
    albedo = sample_texture(atlas, s) * s.tint
    sun = torch.tensor(lighting.sun_direction, dtype=torch.float32, device=device)
    sun = sun / sun.norm()
    lam = (s.normal @ sun).clamp_min_(0.0)[:, None]
    up = (0.5 + 0.5 * s.normal[:, 1])[:, None]
    sky_amb = torch.tensor(lighting.sky_ambient, device=device)
    ground_amb = torch.tensor(lighting.ground_ambient, device=device)
    light = (
        ground_amb
        + (sky_amb - ground_amb) * up
        + lam * torch.tensor(lighting.sun_color, device=device)
    )
    color = albedo * light
    # Fog reaches the horizon colour exactly at the far plane, hiding the clip.
    fog = ((s.t / far).clamp_(0.0, 1.0) ** 2)[:, None]
    horizon = torch.tensor(lighting.horizon, device=device)
    color += (horizon - color) * fog
    out: torch.Tensor = color
    return out


def sky(grid: RayGrid, lighting: Lighting) -> torch.Tensor:
    """(rows, width, 3) linear sky: horizon to zenith by the ray's elevation."""
    dx, dy, dz = (
        grid.field((float(grid.c0[i]), float(grid.cx[i]), float(grid.cy[i])), grid.xs, grid.ys)
        for i in range(3)
    )
    elevation = dy * (dx * dx + dy * dy + dz * dz).rsqrt()
    k = elevation.clamp_(0.0, 1.0).sqrt_()[..., None]
    device = grid.xs.device
    horizon = torch.tensor(lighting.horizon, device=device)
    zenith = torch.tensor(lighting.zenith, device=device)
    return horizon + (zenith - horizon) * k


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Clamp tonemap then the sRGB transfer curve, in [0, 1]."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.pow(1.0 / 2.4) - 0.055)


def quantize_into(srgb: torch.Tensor, out: torch.Tensor) -> None:
    """Write [0, 1] floats as uint8 into ``out``; NaN becomes 0 instead of garbage."""
    q = torch.nan_to_num(srgb, nan=0.0, posinf=1.0, neginf=0.0).mul_(255.0).round_().clamp_(0, 255)
    out.copy_(q)
