"""Depth pass: nearest hit per pixel, in inverse view depth s = 1 / t (0 = sky).

Grounds are infinite planes, so they cover the whole band: s = -dy / oy is one
affine field. Every bounded object is tested only inside its screen rectangle,
and all objects of one shape class at once: the (pixel, object) pairs of all
their rectangles form one list, each pair looks its object's parameters up in
a small per-frame table, and one vectorized pass intersects them all. The
nearest object per pixel comes from one ``scatter_reduce`` (amax) of a packed
int64 key (bits of s, then the object index), which also breaks ties towards
the lower object index like the sequential pass did.

Validity is carried as 0/1 float masks and products, not ``torch.where`` or
boolean indexing (both slow on CPU). NaNs from degenerate rays (a direction
component exactly 0 on a slab boundary) compare false, so they count as misses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from server.game.render.rays import FrameSetup, ObjectInstance, RayGrid, screen_rects
from server.game.render.shapes import Box, Quad, Sphere

ShapeClass = type[Box] | type[Sphere] | type[Quad]

# Low bits of a pair key: 65535 - object index, so that ties go to the lower index.
KEY_SHIFT = 16
KEY_ONE = 1 << KEY_SHIFT
MAX_OBJECTS = KEY_ONE - 1

# Rows of a class table (one column per object), common to every shape class.
A0, AX, AY = 0, 3, 6  # local direction coefficients d_i = a0_i + x ax_i + y ay_i
ORIGIN = 9  # local ray origin, 3 rows
KEY = 12  # 65535 - object index
COMMON_ROWS = 13


@dataclass
class GroundHits:
    """One ground plane's hits over the whole band: s > 0 where it is the nearest ground."""

    inst: ObjectInstance
    s: torch.Tensor  # (rows, width)


@dataclass
class ClassHits:
    """The pixels won by objects of one shape class (n of them)."""

    shape: ShapeClass
    insts: list[ObjectInstance]
    table: torch.Tensor  # (F, K) float32 per-object parameters, see ``class_table``
    pix: torch.Tensor  # (n,) int64 flat index into the band
    oid: torch.Tensor  # (n,) int64 column of ``table``
    sd: torch.Tensor  # (4, n): s, then the local ray direction (3 rows)


@dataclass
class DepthPass:
    s: torch.Tensor  # (rows, width) inverse view depth of the nearest hit, 0 = sky
    grounds: list[GroundHits]
    classes: list[ClassHits]


def fmask(
    cmp: Callable[..., torch.Tensor], a: torch.Tensor, b: torch.Tensor | float
) -> torch.Tensor:
    """``cmp(a, b)`` as a 0/1 float tensor shaped like ``a``: the comparison writes
    straight into float storage (bool results, their ``.float()`` and products with
    them are slow paths on CPU; the values are the same)."""
    return cmp(a, b, out=torch.empty_like(a))


def _ground(setup: FrameSetup, grid: RayGrid, inst: ObjectInstance) -> torch.Tensor | None:
    """s of the plane y = 0 (local) over the band, 0 outside [near, far)."""
    local = inst.local
    oy = float(local[1, :3] @ grid.origin + local[1, 3])
    if oy == 0.0:
        return None  # camera in the plane: t = 0 everywhere, never past near
    a0, ax, ay = grid.direction_coefs(local[:3, :3])[1]
    k = -1.0 / oy
    s = grid.field((a0 * k, ax * k, ay * k), grid.xs, grid.ys)
    # Hit iff near <= t < far (the sequential pass started every pixel at far).
    # (Comparisons written into float tensors: 0/1 masks, much faster than bool ones.)
    m = torch.empty_like(s)
    torch.gt(s, 1.0 / setup.far, out=m)
    s.mul_(m)
    torch.le(s, 1.0 / setup.near, out=m)
    return s.mul_(m)


def class_table(shape: ShapeClass, insts: list[ObjectInstance], grid: RayGrid) -> np.ndarray:
    """(F, K) float64 per-object parameters of one shape class for this band."""
    rows: list[list[float]] = []
    for inst in insts:
        local = inst.local
        o = local[:3, :3] @ grid.origin + local[:3, 3]
        coefs = grid.direction_coefs(local[:3, :3])
        col = [c[0] for c in coefs] + [c[1] for c in coefs] + [c[2] for c in coefs]
        col += [float(o[0]), float(o[1]), float(o[2]), float(MAX_OBJECTS - inst.index)]
        s = inst.obj.shape
        if isinstance(s, Box):
            col += [-h - float(oi) for h, oi in zip(s.half, o, strict=True)]
            col += [h - float(oi) for h, oi in zip(s.half, o, strict=True)]
        elif isinstance(s, Sphere):
            col.append(float(o @ o) - s.radius**2)
        else:
            assert isinstance(s, Quad)
            col += [
                s.width / 2,
                s.height,
                1.0 if s.fence else 0.0,
                1.0 / s.bar_spacing,
                s.bar_width / s.bar_spacing,
                0.25 * s.height,
                0.85 * s.height,
                s.rail_width / 2,
            ]
        rows.append(col)
    return np.asarray(rows, dtype=np.float64).T.copy()


def _pairs(
    rects: list[tuple[int, int, int, int]], grid: RayGrid, xs: np.ndarray, ys: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flat pixel index, object column, sample x and y of every (pixel, object) pair."""
    pix, oid, px, py = [], [], [], []
    for k, (r0, r1, c0, c1) in enumerate(rects):
        nr, nc = r1 - r0, c1 - c0
        pix.append((np.arange(r0, r1)[:, None] * grid.width + np.arange(c0, c1)[None, :]).ravel())
        oid.append(np.full(nr * nc, k, dtype=np.int64))
        px.append(np.tile(xs[c0:c1], nr))
        py.append(np.repeat(ys[r0:r1], nc))
    return np.concatenate(pix), np.concatenate(oid), np.concatenate(px), np.concatenate(py)


def _box_t(p: torch.Tensor, d: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: (t, valid) where t is the entry if past near, else the exit."""
    t_in: torch.Tensor | None = None
    t_out: torch.Tensor | None = None
    for i in range(3):
        inv = d[i].reciprocal()
        ta = inv * p[COMMON_ROWS + i]
        tb = inv.mul_(p[COMMON_ROWS + 3 + i])
        lo, hi = torch.minimum(ta, tb), torch.maximum(ta, tb)
        t_in = lo if t_in is None else torch.maximum(t_in, lo)
        t_out = hi if t_out is None else torch.minimum(t_out, hi)
    assert t_in is not None and t_out is not None
    return t_in, t_out


def _intersect(
    shape: ShapeClass,
    p: torch.Tensor,
    d: list[torch.Tensor],
    near: float,
) -> torch.Tensor:
    """s = 1 / t of each pair's hit, 0 (or NaN) on a miss."""
    if shape is Box:
        t_in, t_out = _box_t(p, d)
        # Entry point if it is past the near plane, else the exit (camera inside or
        # straddling the box: we see its inner faces, like an unculled rasterizer).
        t = torch.lerp(t_out, t_in, fmask(torch.ge, t_in, near))
        valid = fmask(torch.le, t_in, t_out).mul_(fmask(torch.ge, t, near))
        return valid.div_(t)
    o = [p[ORIGIN], p[ORIGIN + 1], p[ORIGIN + 2]]
    if shape is Sphere:
        a = d[0] * d[0]
        a.addcmul_(d[1], d[1]).addcmul_(d[2], d[2])
        b = d[0] * o[0]
        b.addcmul_(d[1], o[1]).addcmul_(d[2], o[2])
        disc = b * b
        disc.addcmul_(a, p[COMMON_ROWS], value=-1.0)
        sq = disc.clamp_min(0.0).sqrt_()
        inv_a = a.reciprocal_()
        t0 = (b + sq).mul_(inv_a).neg_()
        t1 = (sq - b).mul_(inv_a)
        t = torch.lerp(t1, t0, fmask(torch.ge, t0, near))
        valid = fmask(torch.ge, disc, 0.0).mul_(fmask(torch.ge, t, near))
        return valid.div_(t)
    # Quad in local z = 0.
    r = COMMON_ROWS
    t = d[2].reciprocal().mul_(o[2]).neg_()
    qx = torch.addcmul(o[0], t, d[0])
    qy = torch.addcmul(o[1], t, d[1])
    valid = fmask(torch.ge, t, near)
    valid.mul_(fmask(torch.le, qx.abs(), p[r]))
    valid.mul_(fmask(torch.ge, qy, 0.0)).mul_(fmask(torch.le, qy, p[r + 1]))
    if bool((p[r + 2] > 0).any()):
        # Fence: vertical bars every bar_spacing plus two rails; point-sampled, so it aliases.
        phase = torch.frac((qx + p[r]).mul_(p[r + 3]))
        alpha = fmask(torch.lt, phase, p[r + 4])
        half_rail = p[r + 7]
        alpha = torch.maximum(alpha, fmask(torch.lt, (qy - p[r + 5]).abs_(), half_rail))
        alpha = torch.maximum(alpha, fmask(torch.lt, (qy - p[r + 6]).abs_(), half_rail))
        # Non-fence quads: alpha 1.
        alpha = torch.maximum(alpha, 1.0 - p[r + 2])
        valid.mul_(alpha)
    return valid.div_(t)


def depth_pass(setup: FrameSetup, grid: RayGrid) -> DepthPass:
    device = grid.xs.device
    if len(setup.instances) > MAX_OBJECTS:
        raise ValueError(f"at most {MAX_OBJECTS} objects per scene")
    s_ground: torch.Tensor | None = None
    grounds: list[GroundHits] = []
    by_class: dict[ShapeClass, list[ObjectInstance]] = {Box: [], Sphere: [], Quad: []}
    for inst in setup.instances:
        shape = inst.obj.shape
        if isinstance(shape, Box | Sphere | Quad):
            by_class[type(shape)].append(inst)
        else:
            sg = _ground(setup, grid, inst)
            if sg is None:
                continue
            if s_ground is None:
                s_ground = sg
            else:
                # Earlier grounds keep ties; later ones only where strictly nearer.
                sg.mul_(fmask(torch.gt, sg, s_ground))
                for g in grounds:
                    g.s.mul_(fmask(torch.ge, g.s, sg))
                s_ground = torch.maximum(s_ground, sg)
            grounds.append(GroundHits(inst, sg))
    if s_ground is None:
        s_ground = torch.zeros(grid.rows, grid.width, device=device)
    bounded = [i for insts in by_class.values() for i in insts]
    rect_of = dict(zip((i.index for i in bounded), screen_rects(setup, bounded, grid), strict=True))
    xs_np = grid.xs.cpu().numpy()
    ys_np = grid.ys.cpu().numpy()
    keys = torch.zeros(grid.rows * grid.width, dtype=torch.int64, device=device)
    flat_ground = s_ground.view(-1)
    pending = []
    for kind, insts in by_class.items():
        visible = [i for i in insts if rect_of[i.index] is not None]
        if not visible:
            continue
        rects = [r for i in visible if (r := rect_of[i.index]) is not None]
        pix_np, oid_np, x_np, y_np = _pairs(rects, grid, xs_np, ys_np)
        table = torch.from_numpy(class_table(kind, visible, grid).astype(np.float32)).to(device)
        pix = torch.from_numpy(pix_np).to(device)
        oid = torch.from_numpy(oid_np).to(device)
        x = torch.from_numpy(x_np).to(device)
        y = torch.from_numpy(y_np).to(device)
        p = table.index_select(1, oid)
        sd = torch.empty(4, pix.numel(), device=device)
        d = [sd[1], sd[2], sd[3]]
        for i in range(3):
            torch.addcmul(p[A0 + i], p[AX + i], x, out=d[i])
            d[i].addcmul_(p[AY + i], y)
        s = _intersect(kind, p, d, setup.near)
        # Only where nearer than the ground (and than far); NaN (a miss) becomes 0.
        ground = flat_ground.index_select(0, pix).clamp_min_(1.0 / setup.far)
        s.mul_(fmask(torch.gt, s, ground)).nan_to_num_(0.0, 0.0, 0.0)
        sd[0].copy_(s)
        key = s.view(torch.int32).to(torch.int64).mul_(KEY_ONE).add_(p[KEY].to(torch.int64))
        keys.scatter_reduce_(0, pix, key, "amax")
        pending.append((kind, visible, table, pix, oid, sd, key))
    s_all = s_ground
    classes: list[ClassHits] = []
    for kind, visible, table, pix, oid, sd, key in pending:
        won = torch.eq(keys.index_select(0, pix), key).logical_and_(key >= KEY_ONE)
        sel = won.nonzero().view(-1)
        if sel.numel() == 0:
            continue
        if s_all is s_ground:
            s_all = s_ground.clone()
        hits = ClassHits(
            kind, visible, table, pix.index_select(0, sel), oid.index_select(0, sel),
            sd.index_select(1, sel),
        )  # fmt: skip
        s_all.view(-1).index_copy_(0, hits.pix, hits.sd[0])
        classes.append(hits)
    return DepthPass(s_all, grounds, classes)
