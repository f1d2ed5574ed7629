"""Depth pass: nearest hit per pixel over all objects, each only inside its screen rectangle.

Misses are +inf so that one ``minimum`` per object keeps the nearest hit; the
object id is written with ``masked_fill_`` on the pixels it wins. NaNs from
degenerate rays (a direction component exactly 0 on a slab boundary) compare
false everywhere, so they count as misses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from server.render.rays import FrameSetup, ObjectInstance, RayGrid, screen_rect
from server.render.shapes import Box, Ground, Quad, Sphere

INF = math.inf


@dataclass(frozen=True)
class LocalRays:
    """Rays of a rectangle in an object's local frame: origin (3 floats), direction fields."""

    origin: tuple[float, float, float]
    dx: torch.Tensor
    dy: torch.Tensor
    dz: torch.Tensor


def local_rays(
    grid: RayGrid, inst: ObjectInstance, xs: torch.Tensor, ys: torch.Tensor
) -> LocalRays:
    local = inst.local
    o = local[:3, :3] @ grid.origin + local[:3, 3]
    coefs = grid.direction_coefs(local[:3, :3])
    d = [grid.field(c, xs, ys) for c in coefs]
    return LocalRays((float(o[0]), float(o[1]), float(o[2])), d[0], d[1], d[2])


def _keep(t: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
    return torch.where(hit, t, INF)


def hit_ground(r: LocalRays, near: float) -> torch.Tensor:
    t = -r.origin[1] / r.dy
    return _keep(t, t >= near)


def hit_box(r: LocalRays, box: Box, near: float) -> torch.Tensor:
    t_in: torch.Tensor | None = None
    t_out: torch.Tensor | None = None
    for o, d, h in zip(r.origin, (r.dx, r.dy, r.dz), box.half, strict=True):
        inv = d.reciprocal()
        ta = (-h - o) * inv
        tb = (h - o) * inv
        lo, hi = torch.minimum(ta, tb), torch.maximum(ta, tb)
        t_in = lo if t_in is None else torch.maximum(t_in, lo)
        t_out = hi if t_out is None else torch.minimum(t_out, hi)
    assert t_in is not None and t_out is not None
    # Entry point if it is past the near plane, else the exit (camera inside or
    # straddling the box: we see its inner faces, like an unculled rasterizer).
    t = torch.where(t_in >= near, t_in, t_out)
    return _keep(t, (t_in <= t_out) & (t >= near))


def hit_sphere(r: LocalRays, sphere: Sphere, near: float) -> torch.Tensor:
    ox, oy, oz = r.origin
    a = r.dx * r.dx + r.dy * r.dy + r.dz * r.dz
    b = r.dx * ox + r.dy * oy + r.dz * oz
    c = ox * ox + oy * oy + oz * oz - sphere.radius**2
    disc = b * b - a * c
    sq = disc.clamp_min(0.0).sqrt()
    inv_a = a.reciprocal()
    t0 = (-b - sq) * inv_a
    t1 = (-b + sq) * inv_a
    t = torch.where(t0 >= near, t0, t1)
    return _keep(t, (disc >= 0) & (t >= near))


def fence_alpha(qx: torch.Tensor, qy: torch.Tensor, quad: Quad) -> torch.Tensor:
    """Vertical bars every bar_spacing plus two rails; point-sampled, so it aliases."""
    phase = torch.frac((qx + quad.width / 2) / quad.bar_spacing)
    bars = phase < quad.bar_width / quad.bar_spacing
    half_rail = quad.rail_width / 2
    rails = ((qy - 0.25 * quad.height).abs() < half_rail) | (
        (qy - 0.85 * quad.height).abs() < half_rail
    )
    return bars | rails


def hit_quad(r: LocalRays, quad: Quad, near: float) -> torch.Tensor:
    ox, oy, oz = r.origin
    t = -oz / r.dz
    qx = ox + t * r.dx
    qy = oy + t * r.dy
    hit = (t >= near) & (qx.abs() <= quad.width / 2) & (qy >= 0) & (qy <= quad.height)
    if quad.fence:
        hit &= fence_alpha(qx, qy, quad)
    return _keep(t, hit)


def intersect(r: LocalRays, inst: ObjectInstance, near: float) -> torch.Tensor:
    shape = inst.obj.shape
    if isinstance(shape, Ground):
        return hit_ground(r, near)
    if isinstance(shape, Box):
        return hit_box(r, shape, near)
    if isinstance(shape, Sphere):
        return hit_sphere(r, shape, near)
    return hit_quad(r, shape, near)


@dataclass
class DepthPass:
    """Nearest view depth (far where nothing) and object id (-1 = sky) per pixel."""

    t: torch.Tensor  # (rows, width) float32
    ids: torch.Tensor  # (rows, width) int16
    rects: dict[int, tuple[int, int, int, int]]


def depth_pass(setup: FrameSetup, grid: RayGrid) -> DepthPass:
    device = grid.xs.device
    # Starting at `far` clips everything beyond it with the same comparison.
    best = torch.full((grid.rows, grid.width), setup.far, dtype=torch.float32, device=device)
    ids = torch.full((grid.rows, grid.width), -1, dtype=torch.int16, device=device)
    rects: dict[int, tuple[int, int, int, int]] = {}
    for inst in setup.instances:
        rect = screen_rect(setup, inst, grid)
        if rect is None:
            continue
        r0, r1, c0, c1 = rect
        rays = local_rays(grid, inst, grid.xs[c0:c1], grid.ys[r0:r1])
        t = intersect(rays, inst, setup.near)
        best_r = best[r0:r1, c0:c1]
        closer = t < best_r
        torch.minimum(best_r, t, out=best_r)
        ids[r0:r1, c0:c1].masked_fill_(closer, inst.index)
        rects[inst.index] = rect
    return DepthPass(best, ids, rects)
