"""Primary rays of an image band and the per-frame camera/object setup they come from.

A ray direction is kept as an affine function of the sample position,
d(x, y) = c0 + x cx + y cy, with view-space z = -1. Then the hit parameter t
*is* the view depth, every per-pixel direction component is one broadcast add
of a row vector and a column vector, and moving a ray into an object's local
frame is a 3x3 product on the coefficients instead of on every pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from server.game.render.shapes import SceneObject
from server.game.render.transforms import F64Array, rigid_inverse


@dataclass(frozen=True)
class ObjectInstance:
    """A scene object at this frame's time and at the previous frame's time."""

    index: int
    obj: SceneObject
    world: F64Array  # object -> world now
    prev_world: F64Array  # object -> world at the previous frame

    @property
    def local(self) -> F64Array:
        return rigid_inverse(self.world)


@dataclass(frozen=True)
class FrameSetup:
    """Unjittered camera matrices (float64) of this frame and the previous one."""

    rotation: F64Array  # camera -> world 3x3
    origin: F64Array  # camera position, world
    view: F64Array
    proj: F64Array
    prev_view: F64Array
    prev_proj: F64Array
    fov_y_deg: float
    near: float
    far: float
    instances: tuple[ObjectInstance, ...]

    @property
    def view_proj(self) -> F64Array:
        return self.proj @ self.view

    @property
    def prev_view_proj(self) -> F64Array:
        return self.prev_proj @ self.prev_view


@dataclass(frozen=True)
class RayGrid:
    """Rays through the sample positions of rows [y0, y1) of a width x height image."""

    width: int
    height: int
    y0: int
    y1: int
    xs: torch.Tensor  # (width,) sample x in pixels (pixel centre + jitter)
    ys: torch.Tensor  # (y1 - y0,) sample y in pixels
    origin: F64Array
    c0: F64Array  # world direction coefficients, each (3,)
    cx: F64Array
    cy: F64Array

    @property
    def rows(self) -> int:
        return self.y1 - self.y0

    @property
    def pixel_angle(self) -> float:
        """Approximate angle of one pixel at the image centre (radians), for mip selection."""
        return float(np.linalg.norm(self.cy))

    def field(
        self, coef: tuple[float, float, float], xs: torch.Tensor, ys: torch.Tensor
    ) -> torch.Tensor:
        """a0 + x ax + y ay on the (len(ys), len(xs)) grid: one broadcast add per pixel."""
        a0, ax, ay = coef
        return (ys * ay + a0)[:, None] + (xs * ax)[None, :]

    def norm2_terms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """|d|^2 = row[:, None] + col[None, :]: cx and cy are orthogonal, so no xy term."""
        c0, cx, cy = self.c0, self.cx, self.cy
        col = self.xs * (self.xs * float(cx @ cx) + 2.0 * float(c0 @ cx))
        row = self.ys * (self.ys * float(cy @ cy) + 2.0 * float(c0 @ cy)) + float(c0 @ c0)
        return row, col

    def direction_coefs(self, rotation: F64Array) -> list[tuple[float, float, float]]:
        """Per-component (a0, ax, ay) of ``rotation @ d`` (rotation: world -> some frame)."""
        c0, cx, cy = rotation @ self.c0, rotation @ self.cx, rotation @ self.cy
        return [(float(c0[i]), float(cx[i]), float(cy[i])) for i in range(3)]


def make_grid(
    setup: FrameSetup,
    width: int,
    height: int,
    jitter: tuple[float, float],
    y0: int,
    y1: int,
    device: torch.device,
) -> RayGrid:
    """Rays of the unjittered projection through the jittered sample positions."""
    tan_h = math.tan(math.radians(setup.fov_y_deg) / 2.0)
    aspect = width / height
    r = setup.rotation
    # view dir = (ndc_x tan_h aspect, ndc_y tan_h, -1), ndc_x = 2x/W - 1, ndc_y = 1 - 2y/H.
    c0 = r @ np.array([-tan_h * aspect, tan_h, -1.0])
    cx = r @ np.array([2.0 * tan_h * aspect / width, 0.0, 0.0])
    cy = r @ np.array([0.0, -2.0 * tan_h / height, 0.0])
    xs = torch.arange(width, dtype=torch.float32, device=device) + (0.5 + jitter[0])
    ys = torch.arange(y0, y1, dtype=torch.float32, device=device) + (0.5 + jitter[1])
    return RayGrid(width, height, y0, y1, xs, ys, setup.origin, c0, cx, cy)


# The 12 edges of a box, as pairs of indices into its 8 corners (bit i = axis i at max).
_EDGES = np.array([(a, a | (1 << k)) for a in range(8) for k in range(3) if not a & (1 << k)])


def screen_rects(
    setup: FrameSetup, insts: list[ObjectInstance], grid: RayGrid
) -> list[tuple[int, int, int, int] | None]:
    """Band-relative (row0, row1, col0, col1) per bounded object that can see it, None if none.

    Projects the bounding box clipped to the near plane (its corners in front
    plus where its edges cross the plane), so a box partly behind the camera
    still gets a tight rectangle and one wholly behind it none. All objects in
    one vectorized pass.
    """
    if not insts:
        return []
    lo = np.empty((len(insts), 3))
    hi = np.empty((len(insts), 3))
    for k, inst in enumerate(insts):
        bounds = inst.obj.local_bounds()
        assert bounds is not None
        lo[k], hi[k] = bounds
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1  # (8, 3)
    corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])  # (K, 8, 3)
    mats = np.stack([setup.view_proj @ inst.world for inst in insts])  # (K, 4, 4)
    clip = np.einsum("kij,kcj->kci", mats[:, :, :3], corners) + mats[:, None, :, 3]
    # Hits have view depth t >= near; clip slightly in front of it to stay conservative.
    plane = setup.near * 0.999
    a, b = clip[:, _EDGES[:, 0]], clip[:, _EDGES[:, 1]]  # (K, 12, 4)
    wa, wb = a[..., 3] - plane, b[..., 3] - plane
    crosses = wa * wb < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(crosses, wa / (wa - wb), 0.0)
    cut = a + (b - a) * f[..., None]
    pts = np.concatenate([clip, cut], axis=1)  # (K, 20, 4)
    ok = np.concatenate([clip[..., 3] >= plane, crosses], axis=1)
    w = np.where(ok, pts[..., 3], 1.0)
    px = (pts[..., 0] / w + 1.0) * 0.5 * grid.width
    py = (1.0 - pts[..., 1] / w) * 0.5 * grid.height
    inf = np.inf
    x_lo = np.where(ok, px, inf).min(axis=1)
    x_hi = np.where(ok, px, -inf).max(axis=1)
    y_lo = np.where(ok, py, inf).min(axis=1)
    y_hi = np.where(ok, py, -inf).max(axis=1)
    out: list[tuple[int, int, int, int] | None] = []
    for k in range(len(insts)):
        if not ok[k].any():
            out.append(None)
            continue
        # Samples of pixel i lie in [i, i + 1) whatever the jitter: a 2-pixel margin is safe.
        c0 = max(0, math.floor(x_lo[k]) - 2)
        c1 = min(grid.width, math.ceil(x_hi[k]) + 2)
        r0 = max(grid.y0, math.floor(y_lo[k]) - 2) - grid.y0
        r1 = min(grid.y1, math.ceil(y_hi[k]) + 2) - grid.y0
        out.append(None if c0 >= c1 or r0 >= r1 else (r0, r1, c0, c1))
    return out
