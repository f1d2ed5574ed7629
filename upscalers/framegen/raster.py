"""A vectorized scanline rasterizer in torch with a depth test (CPU or CUDA).

Approach, in passes over flat tensors (no Python loop over triangles):

1. Per triangle: the pixel-centre bounding box clipped to the screen, and the
   affine screen-space planes (a = A x + B y + C, like a GPU's plane
   equations) of the barycentrics, the depth and every attribute. Attributes
   are interpolated linearly in screen space, as the paper's vertex shader
   does by writing clip w = 1.
2. Per (triangle, bounding-box row): the exact span of pixel centres inside
   the triangle, solved from the three barycentric half-planes along the row,
   so no candidate pixel is wasted outside the triangle.
3. Per covered (triangle, pixel) fragment, enumerated with
   ``repeat_interleave``: the depth test is one ``scatter_reduce(amin)`` over a
   packed int64 key, (float bits of the NDC depth << 31) | triangle id:
   non-negative floats order like their bit patterns, so the minimum key is
   the nearest fragment and names the winning triangle at the same time.
4. Per pixel: the winner's attribute planes evaluated at the pixel centre.

Triangles whose clipped bounding box exceeds ``max_bbox_pixels`` are dropped
(they come from vertices next to the eye, which a GPU would clip): this bounds
memory and time, and shows up as holes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

KEY_NONE = torch.iinfo(torch.int64).max
TRI_BITS = 31


@dataclass
class Triangles:
    """T triangles in pixel coordinates with per-vertex NDC depth and K attributes."""

    x: torch.Tensor  # (T, 3)
    y: torch.Tensor  # (T, 3)
    z: torch.Tensor  # (T, 3) NDC depth, >= 0
    attrs: torch.Tensor  # (T, 3, K)
    valid: torch.Tensor  # (T,) bool


@dataclass
class Raster:
    """Per pixel (flat, H * W): the winning triangle (0 where none) and its attributes."""

    tri: torch.Tensor  # (H*W,) int64
    covered: torch.Tensor  # (H*W,) bool
    attrs: list[torch.Tensor]  # K x (H*W,) float32, meaningless where not covered


def _planes(tris: Triangles) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Barycentric planes (T, 3, 3) for b0, b1, b2, value planes (T, 1 + K, 3) for z and the
    attributes, each row (A, B, C); and which triangles are usable (T,)."""
    x0, x1, x2 = tris.x.unbind(1)
    y0, y1, y2 = tris.y.unbind(1)
    den = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    ok = tris.valid & (den.abs() > 1e-6)
    inv = torch.where(ok, den, torch.ones_like(den)).reciprocal()
    a1, b1 = (y2 - y0) * inv, (x0 - x2) * inv
    a2, b2 = (y0 - y1) * inv, (x1 - x0) * inv
    c1 = -(a1 * x0 + b1 * y0)
    c2 = -(a2 * x0 + b2 * y0)
    bary = torch.stack(
        (
            torch.stack((-a1 - a2, -b1 - b2, 1.0 - c1 - c2), 1),
            torch.stack((a1, b1, c1), 1),
            torch.stack((a2, b2, c2), 1),
        ),
        1,
    )
    vals = torch.cat((tris.z[..., None], tris.attrs), dim=2)  # (T, 3, 1 + K)
    d1 = vals[:, 1] - vals[:, 0]
    d2 = vals[:, 2] - vals[:, 0]
    pa = a1[:, None] * d1 + a2[:, None] * d2
    pb = b1[:, None] * d1 + b2[:, None] * d2
    pc = vals[:, 0] + c1[:, None] * d1 + c2[:, None] * d2
    return bary, torch.stack((pa, pb, pc), dim=2), ok


def _spans(
    bary: torch.Tensor, tri: torch.Tensor, cy: torch.Tensor, width: int, eps: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last pixel column whose centre on row centre ``cy`` is inside the triangle."""
    pl = bary.index_select(0, tri)  # (S, 3, 3)
    a = pl[:, :, 0]
    c = pl[:, :, 1] * cy[:, None] + pl[:, :, 2] + eps  # b_k(x) + eps = a x + c >= 0
    safe = torch.where(a.abs() > 1e-12, a, torch.ones_like(a))
    root = -c / safe
    inf = torch.full_like(root, float("inf"))
    lo = torch.where(a > 1e-12, root, -inf).amax(1)
    hi = torch.where(a < -1e-12, root, inf).amin(1)
    empty = ((a.abs() <= 1e-12) & (c < 0.0)).any(1) | (lo > hi)
    i0 = torch.ceil(lo.clamp(-1.0, float(width)) - 0.5).clamp_min(0.0)
    i1 = torch.floor(hi.clamp(-1.0, float(width) + 1.0) - 0.5).clamp_max(float(width - 1))
    i1 = torch.where(empty, i0 - 1.0, i1)
    return i0.to(torch.int64), i1.to(torch.int64)


def rasterize(
    tris: Triangles, width: int, height: int, max_bbox_pixels: int, eps: float = 1e-5
) -> Raster:
    dev = tris.x.device
    n_pix = width * height
    bary, planes, ok = _planes(tris)
    bw = (
        torch.floor(tris.x.amax(1) - 0.5).clamp(-1, width - 1)
        - torch.ceil(tris.x.amin(1) - 0.5).clamp(0, width - 1)
        + 1
    ).clamp_min(0)
    iy0 = torch.ceil(tris.y.amin(1) - 0.5).clamp(0, height - 1)
    iy1 = torch.floor(tris.y.amax(1) - 0.5).clamp(-1, height - 1)
    bh = (iy1 - iy0 + 1).clamp_min(0)
    use = ok & (bw * bh <= max_bbox_pixels)
    rows = torch.where(use, bh, torch.zeros_like(bh)).to(torch.int64)

    # One entry per (triangle, row) of its box.
    span_tri = torch.repeat_interleave(rows)
    first = torch.cumsum(rows, 0) - rows
    row = iy0.to(torch.int64).index_select(0, span_tri)
    row = row + torch.arange(span_tri.numel(), device=dev) - first.index_select(0, span_tri)
    cy = row.to(torch.float32) + 0.5
    i0, i1 = _spans(bary, span_tri, cy, width, eps)
    count = (i1 - i0 + 1).clamp_min(0)

    # One entry per fragment: depth along the span is z0 + dz * offset.
    zpl = planes[:, 0].index_select(0, span_tri)  # (S, 3)
    z0 = zpl[:, 0] * (i0.to(torch.float32) + 0.5) + zpl[:, 1] * cy + zpl[:, 2]
    frag_span = torch.repeat_interleave(count)
    offset = torch.arange(frag_span.numel(), device=dev) - (
        torch.cumsum(count, 0) - count
    ).index_select(0, frag_span)
    z = z0.index_select(0, frag_span) + zpl[:, 0].index_select(0, frag_span) * offset.to(
        torch.float32
    )
    zbits = z.clamp_min_(0.0).view(torch.int32).to(torch.int64)
    key = (zbits << TRI_BITS) | span_tri.index_select(0, frag_span)
    dst = (row * width + i0).index_select(0, frag_span) + offset
    zbuf = torch.full((n_pix,), KEY_NONE, dtype=torch.int64, device=dev)
    zbuf.scatter_reduce_(0, dst, key, reduce="amin", include_self=True)

    covered = zbuf != KEY_NONE
    tri = torch.where(covered, zbuf & ((1 << TRI_BITS) - 1), torch.zeros_like(zbuf))
    # Per pixel: the winner's attribute planes at the pixel centre (1-D gathers of
    # contiguous columns are several times faster than gathering (N, k) rows on CPU).
    qx, qy = pixel_centres(width, height, dev)
    attrs = []
    for i in range(1, planes.shape[1]):
        a, b, c = (planes[:, i, j].contiguous().index_select(0, tri) for j in range(3))
        attrs.append(c.addcmul_(a, qx).addcmul_(b, qy))
    return Raster(tri, covered, attrs)


_CENTRES: dict[tuple[int, int, str], tuple[torch.Tensor, torch.Tensor]] = {}


def pixel_centres(
    width: int, height: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat (H * W,) x and y of every pixel centre, cached per size and device."""
    key = (width, height, str(device))
    hit = _CENTRES.get(key)
    if hit is None:
        xs = torch.arange(width, device=device, dtype=torch.float32) + 0.5
        ys = torch.arange(height, device=device, dtype=torch.float32) + 0.5
        hit = (xs.repeat(height), ys.repeat_interleave(width))
        if len(_CENTRES) > 8:
            _CENTRES.clear()
        _CENTRES[key] = hit
    return hit
