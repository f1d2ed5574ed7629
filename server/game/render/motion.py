"""Motion vectors and depth from the depth pass, both with unjittered projections.

With s = 1 / t (0 for sky), the hit point is o + d / s, and in homogeneous
coordinates M (o + d / s, 1) ~ s M (o, 1) + M (d, 0). So one formula projects
surfaces and sky directions (points at infinity, which drop the translation)
alike, and every term is an affine field of the sample position.

Motion is "previous position minus current position", both computed by the
same code from the same inputs, so a still camera over a still scene gives
exactly 0 whatever the jitter, instead of a rounding residue. The pixel scale
(W/2 and -H/2) is folded into the matrices' x and y rows, and the +1 offsets of
the NDC -> pixel map cancel in the difference.
"""

from __future__ import annotations

import numpy as np
import torch

from server.game.render.rays import FrameSetup, RayGrid
from server.game.render.transforms import F64Array

# Points behind the previous camera have no meaningful position there; clamp
# rather than let 1/w blow up into inf.
MIN_W = 1e-6


def depth_from_s(
    s: torch.Tensor, setup: FrameSetup, out: torch.Tensor | None = None
) -> torch.Tensor:
    """NDC z = far/(far-near) (1 - near/t); sky (s = 0) clamps to exactly 1.0."""
    a = setup.far / (setup.far - setup.near)
    res = torch.mul(s, -a * setup.near, out=out) if out is not None else s * (-a * setup.near)
    return res.add_(a).clamp_(0.0, 1.0)


def _pixel_rows(m: F64Array, grid: RayGrid) -> F64Array:
    """Rows x, y, w of clip matrix ``m`` with x, y scaled to pixel offsets."""
    return np.stack([m[0] * (0.5 * grid.width), m[1] * (-0.5 * grid.height), m[3]])


def _project_field(
    m: F64Array, grid: RayGrid, s: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel position (less the constant centre offset) of every sample under ``m``."""
    rows = _pixel_rows(m, grid)
    mo = rows @ np.append(grid.origin, 1.0)
    m3 = rows[:, :3]
    c0, cx, cy = m3 @ grid.c0, m3 @ grid.cx, m3 @ grid.cy

    def comp(i: int) -> torch.Tensor:
        f = grid.field((float(c0[i]), float(cx[i]), float(cy[i])), grid.xs, grid.ys)
        return f.add_(s, alpha=float(mo[i]))

    inv_w = comp(2).clamp_min_(MIN_W).reciprocal_()
    return comp(0).mul_(inv_w), comp(1).mul_(inv_w)


def static_motion(
    setup: FrameSetup, grid: RayGrid, s: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, width) x and y motion of a static world under the camera change."""
    px0, py0 = _project_field(setup.prev_view_proj, grid, s)
    px1, py1 = _project_field(setup.view_proj, grid, s)
    return px0.sub_(px1), py0.sub_(py1)


def _project_points(
    m: F64Array, q: torch.Tensor, grid: RayGrid
) -> tuple[torch.Tensor, torch.Tensor]:
    rows = torch.as_tensor(_pixel_rows(m, grid), dtype=torch.float32, device=q.device)
    clip = rows[:, :3] @ q + rows[:, 3:]
    inv_w = clip[2].clamp_min(MIN_W).reciprocal_()
    return clip[0] * inv_w, clip[1] * inv_w


def object_motion(
    setup: FrameSetup,
    grid: RayGrid,
    world: F64Array,
    prev_world: F64Array,
    q: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """x and y motion of a moving object's pixels from their (3, n) local hit points."""
    px0, py0 = _project_points(setup.prev_view_proj @ prev_world, q, grid)
    px1, py1 = _project_points(setup.view_proj @ world, q, grid)
    return px0.sub_(px1), py0.sub_(py1)
