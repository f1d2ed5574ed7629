"""Attribute pass: for the pixels each object won, what the shader needs.

Bounded objects run once per shape class on exactly the pixels that class won
(gathered by index), looking per-object parameters up in a small table, so
every hit pixel is shaded once whatever the overdraw of the depth pass. Grounds
run over the band rows that contain them, as affine fields.

A surface is a set of rows of equal length (see ``SURFACE_ROWS``): texture
coordinates in repeats, texture index, the mip footprint, linear tint, the two
lighting terms of the normal (sun cosine and world up component), and s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from server.game.render.intersect import ORIGIN, ClassHits, GroundHits, fmask
from server.game.render.rays import FrameSetup, ObjectInstance, RayGrid
from server.game.render.scene import Lighting
from server.game.render.shapes import Box, Ground, Material, Quad, Sphere
from server.game.render.textures import SIZE, TextureAtlas

U, V, TEX, FOOT, TINT, LAM, NY, S = 0, 1, 2, 3, 4, 7, 8, 9
SURFACE_ROWS = 10


@dataclass(frozen=True)
class MaterialEntry:
    texture: float  # texture index in the atlas
    tint: tuple[float, float, float]
    # log2(texels per metre); the mip level adds log2 of the pixel footprint in metres.
    lod_bias: float
    tile: tuple[float, float]
    mip: bool

    def footprint_scale(self, pixel_angle: float) -> float:
        """Factor f with mip level = floor(log2(f * dist * rsqrt(cos))) (0 without mips).

        That is round(log2(footprint) + lod_bias), the footprint being
        dist * pixel_angle * rsqrt(cos): adding 0.5 before the floor rounds.
        """
        return pixel_angle * 2.0 ** (self.lod_bias + 0.5) if self.mip else 0.0


def material_entry(m: Material, atlas: TextureAtlas, lod_bias: float = 0.0) -> MaterialEntry:
    bias = math.log2(SIZE / math.sqrt(m.tile[0] * m.tile[1])) + lod_bias
    return MaterialEntry(float(atlas.index(m.texture)), m.tint, bias, m.tile, m.mip)


def sun_direction(lighting: Lighting) -> np.ndarray:
    sun = np.asarray(lighting.sun_direction, dtype=np.float64)
    return sun / np.linalg.norm(sun)


def _attr_table(
    hits: ClassHits,
    entries: dict[str, MaterialEntry],
    grid: RayGrid,
    sun: np.ndarray,
) -> torch.Tensor:
    """(F, K) per object: material, local sun and up, shape parameters."""
    cols = []
    for inst in hits.insts:
        e = entries[inst.obj.material]
        rot = inst.world[:3, :3]
        sun_l = rot.T @ sun
        up_l = rot[1]  # rot.T @ (0, 1, 0)
        col = [
            e.texture,
            1.0 / e.tile[0],
            1.0 / e.tile[1],
            e.footprint_scale(grid.pixel_angle),
            *e.tint,
            *(float(c) for c in sun_l),
            *(float(c) for c in up_l),
        ]
        s = inst.obj.shape
        if isinstance(s, Box):
            col += [*(1.0 / h for h in s.half), *s.half]
        elif isinstance(s, Sphere):
            col += [1.0 / s.radius, s.radius]
        else:
            assert isinstance(s, Quad)
            col += [s.width / 2, s.height]
        cols.append(col)
    table = torch.from_numpy(np.asarray(cols, dtype=np.float32).T.copy())
    return table.to(hits.pix.device)


# Rows of the attribute table.
_TEX, _ITU, _ITV, _FS, _TINT, _SUN, _UP, _SHAPE = 0, 1, 2, 3, 4, 7, 10, 13


def object_surface(
    hits: ClassHits, entries: dict[str, MaterialEntry], grid: RayGrid, sun: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """(SURFACE_ROWS, n) surface of one class's pixels, and (3, n) local hit points."""
    n = hits.pix.numel()
    device = hits.pix.device
    attr = _attr_table(hits, entries, grid, sun).index_select(1, hits.oid)
    # Only the local ray origin of the class table is needed here.
    origin = hits.table[ORIGIN : ORIGIN + 3].index_select(1, hits.oid)
    s = hits.sd[0]
    d = [hits.sd[1], hits.sd[2], hits.sd[3]]
    t = s.reciprocal()
    q = torch.empty(3, n, device=device)
    for i in range(3):
        torch.addcmul(origin[i], d[i], t, out=q[i])
    dn = d[0] * d[0]
    dn.addcmul_(d[1], d[1]).addcmul_(d[2], d[2]).sqrt_()
    out = torch.empty(SURFACE_ROWS, n, device=device)
    sh = _SHAPE
    nl: list[torch.Tensor | None]
    if hits.shape is Box:
        a = [q[i].abs().mul_(attr[sh + i]) for i in range(3)]
        is_x = fmask(torch.ge, a[0], a[1]).mul_(fmask(torch.ge, a[0], a[2]))
        is_y = fmask(torch.gt, a[1], a[0]).mul_(fmask(torch.ge, a[1], a[2]))
        is_z = 1.0 - is_x - is_y
        nl = [is_x * q[0].sign(), is_y * q[1].sign(), is_z.mul_(q[2].sign())]
        zu = q[2] + attr[sh + 5]
        torch.lerp(q[0] + attr[sh + 3], zu, is_x, out=out[U])
        torch.lerp(attr[sh + 4] - q[1], zu, is_y, out=out[V])
    elif hits.shape is Sphere:
        inv_r, r = attr[sh], attr[sh + 1]
        ns = [q[i] * inv_r for i in range(3)]
        torch.addcmul(r * math.pi, torch.atan2(q[2], q[0]), r, out=out[U])
        torch.mul(torch.acos(ns[1].clamp(-1.0, 1.0)), r, out=out[V])
        nl = list(ns)
    else:
        nl = [None, None, None]
        torch.add(q[0], attr[sh], out=out[U])
        torch.sub(attr[sh + 1], q[1], out=out[V])
    out[U].mul_(attr[_ITU])
    out[V].mul_(attr[_ITV])
    out[TEX].copy_(attr[_TEX])
    out[TINT : TINT + 3].copy_(attr[_TINT : _TINT + 3])
    out[S].copy_(s)
    # Two-sided: turn the normal towards the viewer (inner box faces, backs of quads).
    comps = [(c, d[i], i) for i, c in enumerate(nl) if c is not None]
    if comps:
        facing = comps[0][0] * comps[0][1]
        for c, di, _ in comps[1:]:
            facing.addcmul_(c, di)
    else:  # quad: local normal +z
        facing = d[2].clone()
        comps = [(torch.ones(n, device=device), d[2], 2)]
    flip = fmask(torch.gt, facing, 0.0).mul_(-2.0).add_(1.0)
    lam = out[LAM]
    ny = out[NY]
    lam.zero_()
    ny.zero_()
    for c, _, i in comps:
        lam.addcmul_(c, attr[_SUN + i])
        ny.addcmul_(c, attr[_UP + i])
    lam.mul_(flip).clamp_min_(0.0)
    ny.mul_(flip)
    # Footprint grows as 1/cos at grazing angles; the square root splits the
    # difference between over-blurring (isotropic max) and shimmer.
    cos = facing.abs_().div_(dn).clamp_(0.02, 1.0)
    foot = out[FOOT]
    torch.mul(dn, t, out=foot)
    foot.mul_(cos.rsqrt_()).mul_(attr[_FS])
    return out, q


@dataclass
class GroundSurface:
    """A ground's surface over band rows [r0, r1), and its constant lighting terms."""

    r0: int
    r1: int
    rows: torch.Tensor  # (SURFACE_ROWS, r1 - r0, width); LAM, NY unused
    lam: float
    ny: float


def ground_surface(
    g: GroundHits,
    entries: dict[str, MaterialEntry],
    setup: FrameSetup,
    grid: RayGrid,
    rows: tuple[int, int],
    sun: np.ndarray,
) -> GroundSurface:
    inst: ObjectInstance = g.inst
    shape = inst.obj.shape
    assert isinstance(shape, Ground)
    r0, r1 = rows
    xs, ys = grid.xs, grid.ys[r0:r1]
    local = inst.local
    o = local[:3, :3] @ grid.origin + local[:3, 3]
    coefs = grid.direction_coefs(local[:3, :3])
    s = g.s[r0:r1].clamp_min(1.0 / setup.far)  # sky pixels: finite, blended away later
    t = s.reciprocal_()
    out = torch.empty(SURFACE_ROWS, r1 - r0, grid.width, device=xs.device)
    qx = grid.field(coefs[0], xs, ys).mul_(t).add_(float(o[0]))
    qz = grid.field(coefs[2], xs, ys).mul_(t).add_(float(o[2]))
    e = entries[inst.obj.material]
    fs = e.footprint_scale(grid.pixel_angle)
    params = [e.texture, 1.0 / e.tile[0], 1.0 / e.tile[1], fs, *e.tint]
    targets = [out[TEX], out[U], out[V], out[FOOT], out[TINT], out[TINT + 1], out[TINT + 2]]
    if shape.path_material is not None:
        p = entries[shape.path_material]
        fp = p.footprint_scale(grid.pixel_angle)
        path = [p.texture, 1.0 / p.tile[0], 1.0 / p.tile[1], fp, *p.tint]
        on_path = fmask(torch.lt, qx.abs(), shape.path_half_width)
        for dst, a, b in zip(targets, params, path, strict=True):
            torch.mul(on_path, b - a, out=dst).add_(a)
    else:
        for dst, a in zip(targets, params, strict=True):
            dst.fill_(a)
    out[U].mul_(qx)
    out[V].mul_(qz)
    out[S].copy_(g.s[r0:r1])
    # Normal: local +y, turned towards the viewer (who is on the side of oy).
    flip = 1.0 if o[1] > 0 else -1.0
    n_world = inst.world[:3, 1] * flip
    row, col = grid.norm2_terms()
    dn = (row[r0:r1, None] + col[None, :]).sqrt_()
    cos = grid.field(coefs[1], xs, ys).abs_().div_(dn).clamp_(0.02, 1.0)
    foot = out[FOOT]
    foot.mul_(dn).mul_(t).mul_(cos.rsqrt_())
    lam = max(0.0, float(n_world @ sun))
    return GroundSurface(r0, r1, out, lam, float(n_world[1]))
