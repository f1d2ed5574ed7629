"""Motion vectors and depth from the depth pass, both with unjittered projections.

With s = 1 / t (0 for sky), the hit point is o + d / s, and in homogeneous
coordinates M (o + d / s, 1) ~ s M (o, 1) + M (d, 0). So one formula projects
surfaces and sky directions (points at infinity, which drop the translation)
alike, and every term is an affine field of the sample position.

Motion is "previous position minus current position", both computed by the
same code from the same inputs, so a still camera over a still scene gives
exactly 0 whatever the jitter, instead of a rounding residue.
"""

from __future__ import annotations

import numpy as np
import torch

from server.render.rays import FrameSetup, ObjectInstance, RayGrid
from server.render.transforms import F64Array

# Points behind the previous camera have no meaningful position there; clamp
# rather than let 1/w blow up into inf.
MIN_W = 1e-6


def depth_from_s(s: torch.Tensor, setup: FrameSetup) -> torch.Tensor:
    """NDC z = far/(far-near) (1 - near/t); sky (s = 0) clamps to exactly 1.0."""
    a = setup.far / (setup.far - setup.near)
    return (a - (a * setup.near) * s).clamp_(0.0, 1.0)


def _project_field(
    m: F64Array, grid: RayGrid, s: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel position of every sample under clip matrix ``m`` (world -> clip)."""
    mo = m @ np.append(grid.origin, 1.0)
    m3 = m[:, :3]
    c0, cx, cy = m3 @ grid.c0, m3 @ grid.cx, m3 @ grid.cy

    def comp(i: int) -> torch.Tensor:
        f = grid.field((float(c0[i]), float(cx[i]), float(cy[i])), grid.xs, grid.ys)
        return s * float(mo[i]) + f

    w = comp(3).clamp_min_(MIN_W)
    inv_w = w.reciprocal_()
    px = (comp(0) * inv_w + 1.0) * (0.5 * grid.width)
    py = (1.0 - comp(1) * inv_w) * (0.5 * grid.height)
    return px, py


def static_motion(setup: FrameSetup, grid: RayGrid, s: torch.Tensor) -> torch.Tensor:
    """(rows, width, 2) motion of a static world under the camera change."""
    px0, py0 = _project_field(setup.prev_view_proj, grid, s)
    px1, py1 = _project_field(setup.view_proj, grid, s)
    return torch.stack([px0 - px1, py0 - py1], dim=-1)


def _project_points(
    m: F64Array, p: torch.Tensor, grid: RayGrid
) -> tuple[torch.Tensor, torch.Tensor]:
    mt = torch.as_tensor(m, dtype=torch.float32, device=p.device)
    clip = p @ mt[:, :3].T + mt[:, 3]
    inv_w = clip[:, 3].clamp_min(MIN_W).reciprocal()
    px = (clip[:, 0] * inv_w + 1.0) * (0.5 * grid.width)
    py = (1.0 - clip[:, 1] * inv_w) * (0.5 * grid.height)
    return px, py


def object_motion(
    setup: FrameSetup, grid: RayGrid, inst: ObjectInstance, flat: torch.Tensor, t: torch.Tensor
) -> torch.Tensor:
    """(n, 2) motion of a moving object's pixels: local point, previous pose, previous camera."""
    rows = torch.div(flat, grid.width, rounding_mode="floor")
    cols = flat - rows * grid.width
    xs, ys = grid.xs[cols], grid.ys[rows]
    d = [float(grid.c0[i]) + xs * float(grid.cx[i]) + ys * float(grid.cy[i]) for i in range(3)]
    p = torch.stack([float(grid.origin[i]) + t * d[i] for i in range(3)], dim=1)
    # World now -> object local -> world at the previous frame -> previous clip.
    prev = setup.prev_view_proj @ inst.prev_world @ inst.local
    px0, py0 = _project_points(prev, p, grid)
    px1, py1 = _project_points(setup.view_proj, p, grid)
    return torch.stack([px0 - px1, py0 - py1], dim=1)
