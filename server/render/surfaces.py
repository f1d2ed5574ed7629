"""Attribute pass: for the pixels each object won, its normal, texture coordinates and mip level.

Runs once per object on exactly its own pixels (gathered by index), so every
hit pixel is shaded once, whatever the overdraw of the depth pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from server.render.intersect import DepthPass
from server.render.rays import FrameSetup, ObjectInstance, RayGrid
from server.render.shapes import Box, Ground, Material, Quad, Sphere
from server.render.textures import SIZE, TextureAtlas


@dataclass(frozen=True)
class MaterialEntry:
    texture: float  # texture index in the atlas
    tint: tuple[float, float, float]
    # log2(texels per metre); the mip level adds log2 of the pixel footprint in metres.
    lod_bias: float
    tile: tuple[float, float]
    mip: bool


def material_entry(m: Material, atlas: TextureAtlas, lod_bias: float = 0.0) -> MaterialEntry:
    bias = math.log2(SIZE / math.sqrt(m.tile[0] * m.tile[1])) + lod_bias
    return MaterialEntry(float(atlas.index(m.texture)), m.tint, bias, m.tile, m.mip)


@dataclass
class Surface:
    """Per hit pixel (all tensors length n) of one or several objects."""

    flat: torch.Tensor  # int64 index into the band, row-major
    dist: torch.Tensor  # distance along the ray (metres)
    t: torch.Tensor  # view depth
    normal: torch.Tensor  # (n, 3) world, facing the viewer
    u: torch.Tensor  # texture repeats
    v: torch.Tensor
    texture: torch.Tensor  # float texture index
    lod: torch.Tensor
    tint: torch.Tensor  # (n, 3)

    @staticmethod
    def cat(parts: list[Surface]) -> Surface:
        return Surface(
            *(torch.cat([getattr(p, f) for p in parts]) for f in Surface.__dataclass_fields__)
        )


def _select(
    ids: torch.Tensor, rect: tuple[int, int, int, int], index: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r0, r1, c0, c1 = rect
    nz = (ids[r0:r1, c0:c1] == index).nonzero()
    rows = nz[:, 0] + r0
    cols = nz[:, 1] + c0
    return rows, cols, rows * width + cols


def _lod(
    entry_lod: torch.Tensor | float,
    dist: torch.Tensor,
    cos: torch.Tensor,
    pixel_angle: float,
) -> torch.Tensor:
    # Footprint grows as 1/cos at grazing angles; the square root splits the
    # difference between over-blurring (isotropic max) and shimmer.
    footprint = dist * pixel_angle * cos.clamp_min(0.02).rsqrt()
    return footprint.clamp_min(1e-12).log2() + entry_lod


def surface_of(
    inst: ObjectInstance,
    entries: dict[str, MaterialEntry],
    setup: FrameSetup,
    grid: RayGrid,
    depth: DepthPass,
) -> Surface | None:
    rect = depth.rects.get(inst.index)
    if rect is None:
        return None
    rows, cols, flat = _select(depth.ids, rect, inst.index, grid.width)
    n = flat.numel()
    if n == 0:
        return None
    device = flat.device
    xs, ys = grid.xs[cols], grid.ys[rows]
    t = depth.t.view(-1)[flat]
    local = inst.local
    o = local[:3, :3] @ grid.origin + local[:3, 3]
    d = [a0 + xs * ax + ys * ay for a0, ax, ay in grid.direction_coefs(local[:3, :3])]
    q = [float(o[i]) + t * d[i] for i in range(3)]
    dnorm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
    dist = t * dnorm
    shape = inst.obj.shape
    entry = entries[inst.obj.material]
    zero = torch.zeros(n, device=device)
    one = torch.ones(n, device=device)
    texture: torch.Tensor = torch.full((n,), entry.texture, device=device)
    tint: torch.Tensor = torch.tensor(entry.tint, device=device).expand(n, 3)
    lod_bias: torch.Tensor | float = entry.lod_bias
    mip: torch.Tensor | float = 1.0 if entry.mip else 0.0
    tile_u: torch.Tensor | float = entry.tile[0]
    tile_v: torch.Tensor | float = entry.tile[1]
    if isinstance(shape, Ground):
        nl = [zero, one, zero]
        um, vm = q[0], q[2]
        if shape.path_material is not None:
            path = entries[shape.path_material]
            on_path = q[0].abs() < shape.path_half_width
            texture = torch.where(on_path, path.texture, entry.texture)
            tint = torch.where(on_path[:, None], torch.tensor(path.tint, device=device), tint)
            lod_bias = torch.where(on_path, path.lod_bias, entry.lod_bias)
            tile_u = torch.where(on_path, path.tile[0], entry.tile[0])
            tile_v = torch.where(on_path, path.tile[1], entry.tile[1])
    elif isinstance(shape, Box):
        hx, hy, hz = shape.half
        a = [q[0].abs() / hx, q[1].abs() / hy, q[2].abs() / hz]
        is_x = ((a[0] >= a[1]) & (a[0] >= a[2])).float()
        is_y = ((a[1] > a[0]) & (a[1] >= a[2])).float()
        is_z = 1.0 - is_x - is_y
        nl = [is_x * q[0].sign(), is_y * q[1].sign(), is_z * q[2].sign()]
        um = is_x * (q[2] + hz) + (1.0 - is_x) * (q[0] + hx)
        vm = is_y * (q[2] + hz) + (1.0 - is_y) * (hy - q[1])
    elif isinstance(shape, Sphere):
        r = shape.radius
        nl = [q[0] / r, q[1] / r, q[2] / r]
        um = (torch.atan2(q[2], q[0]) / (2 * math.pi) + 0.5) * (2 * math.pi * r)
        vm = torch.acos((q[1] / r).clamp(-1.0, 1.0)) * r
    else:
        assert isinstance(shape, Quad)
        nl = [zero, zero, one]
        um = q[0] + shape.width / 2
        vm = shape.height - q[1]
    # Two-sided: turn the normal towards the viewer (inner box faces, backs of quads).
    facing = nl[0] * d[0] + nl[1] * d[1] + nl[2] * d[2]
    flip = 1.0 - 2.0 * (facing > 0).float()
    nl = [c * flip for c in nl]
    cos = (facing.abs() / dnorm).clamp_max(1.0)
    lod = _lod(lod_bias, dist, cos, grid.pixel_angle) * mip
    rot = inst.world[:3, :3]
    normal = torch.stack(
        [
            float(rot[i, 0]) * nl[0] + float(rot[i, 1]) * nl[1] + float(rot[i, 2]) * nl[2]
            for i in range(3)
        ],
        dim=1,
    )
    return Surface(flat, dist, t, normal, um / tile_u, vm / tile_v, texture, lod, tint)
