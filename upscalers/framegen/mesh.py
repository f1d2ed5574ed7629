"""The screen-space aggregated mesh (SSAM) of Mesh Projection Estimation.

Step 1 of the paper: one vertex per n x n tile at the pixel of largest
squared depth gradient ``(D[x+1,y]-D[x,y])^2 + (D[x,y+1]-D[x,y])^2``; flat
tiles keep the first pixel (upper left), as the paper's loop does.
Step 2: reproject the vertices with ``P_k V_k V_{k-1}^-1 P_{k-1}^-1`` and keep
position and UV (the source pixel coordinate).

Tensile correction (the paper's compute-shader step): among the 3 x 3
neighbours of the chosen pixel take the nearest (foreground) and farthest
(background) pixel. The vertex sits on the foreground pixel's reprojected
position; when foreground and background keep their relative direction but
separate by more than a threshold after reprojection, the vertex takes the
background pixel's UV ("tiny UV bias"), so the triangles stretched across the
opened gap sample background instead of smearing the foreground.

Screen edges: an outer ring of vertices is added around the tile vertices
and pinned to the border (x = 0 / W with u = 0 / W on the left and right,
y = 0 / H with v = 0 / H on top and bottom, the other coordinate following
the adjacent tile vertex), as the paper's vertex shader anchors edge vertices,
so the predicted image has no gap at the frame edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from upscalers.framegen.geometry import reproject_points
from upscalers.framegen.raster import Triangles


@dataclass(frozen=True)
class MeshOptions:
    tile: int = 16
    tensile: bool = True
    # Growth (pixels) of the foreground/background separation that counts as a tear.
    tensile_threshold_px: float = 1.0


def vertex_pixels(depth: torch.Tensor, dynamic: torch.Tensor, tile: int) -> torch.Tensor:
    """(Th, Tw, 2) int64 (x, y) of each tile's largest squared depth gradient.

    Sizes the tile does not divide are padded with a gradient below any real
    one, so a partial tile picks one of its own pixels. Dynamic pixels lose
    to every static pixel of their tile (the game redraws moving objects).
    """
    h, w = depth.shape
    g = torch.zeros_like(depth)
    dx = depth[:, 1:] - depth[:, :-1]
    dy = depth[1:, :] - depth[:-1, :]
    g[:, :-1] += dx * dx
    g[:-1, :] += dy * dy
    g = torch.where(dynamic, torch.full_like(g, -1.0), g)
    th, tw = -(-h // tile), -(-w // tile)
    g = F.pad(g, (0, tw * tile - w, 0, th * tile - h), value=-2.0)
    blocks = g.view(th, tile, tw, tile).permute(0, 2, 1, 3).reshape(th, tw, tile * tile)
    best = blocks.argmax(dim=2)
    ty = torch.arange(th, device=depth.device)[:, None]
    tx = torch.arange(tw, device=depth.device)[None, :]
    vy = ty * tile + torch.div(best, tile, rounding_mode="floor")
    vx = tx * tile + best % tile
    return torch.stack((vx, vy), dim=-1)


def _neighbour_extremes(
    depth: torch.Tensor, vxy: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(x, y) of the nearest and the farthest pixel in each vertex's 3 x 3 neighbourhood."""
    h, w = depth.shape
    off = torch.tensor(
        [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], device=depth.device
    )  # (9, 2)
    nb = vxy[..., None, :] + off  # (Th, Tw, 9, 2)
    nb[..., 0].clamp_(0, w - 1)
    nb[..., 1].clamp_(0, h - 1)
    d = depth.view(-1)[nb[..., 1] * w + nb[..., 0]]  # (Th, Tw, 9)
    # Ties go to the centre pixel (index 4): argmin/argmax return the first, so
    # bias the centre by a hair.
    bias = torch.zeros(9, device=depth.device, dtype=depth.dtype)
    bias[4] = 1e-9
    fg = (d - bias).argmin(dim=2)
    bg = (d + bias).argmax(dim=2)
    take = torch.gather
    fgxy = take(nb, 2, fg[..., None, None].expand(*fg.shape, 1, 2)).squeeze(2)
    bgxy = take(nb, 2, bg[..., None, None].expand(*bg.shape, 1, 2)).squeeze(2)
    return fgxy, bgxy


def _pin_ring(t: torch.Tensor) -> torch.Tensor:
    """(Th, Tw) -> (Th + 2, Tw + 2) by copying the adjacent row / column outward."""
    return F.pad(t[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]


def build_mesh(
    depth_eff: torch.Tensor,
    depth_raw: torch.Tensor,
    dynamic: torch.Tensor,
    reproj: torch.Tensor,
    opts: MeshOptions,
) -> Triangles:
    """Triangles of the reprojected SSAM; attributes are the source (u, v) in pixels.

    ``depth_raw`` (sky = 1.0) drives the gradient search, ``depth_eff`` (sky at
    the plane at infinity) the reprojection; ``reproj`` is the (4, 4) forward
    matrix in float64.
    """
    h, w = depth_raw.shape
    dev = depth_raw.device
    vxy = vertex_pixels(depth_raw, dynamic, opts.tile)
    f64 = torch.float64

    def project(xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        d = depth_eff.view(-1)[xy[..., 1] * w + xy[..., 0]].to(f64)
        p = reproject_points(reproj, xy[..., 0].to(f64) + 0.5, xy[..., 1].to(f64) + 0.5, d, w, h)
        return p.px, p.py, p.depth, p.valid

    if opts.tensile:
        fgxy, bgxy = _neighbour_extremes(depth_raw, vxy)
        fx, fy, fz, fv = project(fgxy)
        bx, by, _, bv = project(bgxy)
        before = (fgxy - bgxy).to(f64)
        after_x, after_y = fx - bx, fy - by
        same_dir = before[..., 0] * after_x + before[..., 1] * after_y > 0.0
        grow = torch.hypot(after_x, after_y) - torch.hypot(before[..., 0], before[..., 1])
        tear = fv & bv & same_dir & (grow > opts.tensile_threshold_px)
        uvxy = torch.where(tear[..., None], bgxy, fgxy)
        x, y, z, valid = fx, fy, fz, fv
    else:
        uvxy = vxy
        x, y, z, valid = project(vxy)

    u = uvxy[..., 0].to(f64) + 0.5
    v = uvxy[..., 1].to(f64) + 0.5
    x, y, z, u, v = (_pin_ring(t) for t in (x, y, z, u, v))
    valid = _pin_ring(valid.to(f64)) > 0.5
    x[:, 0], x[:, -1], u[:, 0], u[:, -1] = 0.0, float(w), 0.0, float(w)
    y[0, :], y[-1, :], v[0, :], v[-1, :] = 0.0, float(h), 0.0, float(h)

    # Two triangles per cell: (00, 01, 11) and (00, 11, 10).
    def corners(t: torch.Tensor) -> torch.Tensor:
        c00, c01, c10, c11 = t[:-1, :-1], t[:-1, 1:], t[1:, :-1], t[1:, 1:]
        a = torch.stack((c00, c01, c11), dim=-1).reshape(-1, 3)
        b = torch.stack((c00, c11, c10), dim=-1).reshape(-1, 3)
        return torch.cat((a, b), dim=0)

    f32 = torch.float32
    tv = corners(valid.to(f32)).amin(dim=1) > 0.5
    attrs = torch.stack((corners(u), corners(v)), dim=-1).to(f32)
    return Triangles(
        corners(x).to(f32), corners(y).to(f32), corners(z).to(f32).clamp_min(0.0), attrs, tv.to(dev)
    )
