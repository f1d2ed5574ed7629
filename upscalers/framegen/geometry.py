"""Reprojection between the cached camera and a new one (conventions of server/frames/frame.py).

A cached pixel at continuous position (x, y) with NDC depth z has NDC
(2x/W - 1, 1 - 2y/H, z). The paper's reprojection matrix
``R = P_k V_k V_{k-1}^-1 P_{k-1}^-1`` takes it to the new clip space.

Sky (depth exactly 1.0) is a direction, not the far plane: it must move with
the rotation only. ``P^-1`` maps the NDC depth ``z_inf`` where the homogeneous
view w vanishes to the plane at infinity, so replacing a sky depth by
``z_inf`` (1.0005 for near 0.1, far 200) lets the same matrix reproject sky
pixels as directions, with no special case further on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

F64Array = npt.NDArray[np.float64]

# A clip w below this is on or behind the new camera's eye: such points are culled.
MIN_CLIP_W = 1e-6


def _finite_inverses(ms: F64Array) -> F64Array | None:
    """Inverses of a stack of matrices (one batched call), or None if any is non-finite or
    singular."""
    if not np.all(np.isfinite(ms)):
        return None
    try:
        inv = np.linalg.inv(ms)
    except np.linalg.LinAlgError:
        return None
    return np.asarray(inv, dtype=np.float64) if np.all(np.isfinite(inv)) else None


@dataclass(frozen=True)
class Reprojection:
    """Cached NDC -> new clip (``forward``) and new NDC -> cached clip (``inverse``)."""

    forward: F64Array  # (4, 4) P_k V_k V_{k-1}^-1 P_{k-1}^-1
    inverse: F64Array  # (4, 4) its inverse
    cached_z_inf: float  # cached NDC depth of the plane at infinity
    new_z_inf: float  # new NDC depth of the plane at infinity

    @staticmethod
    def between(
        cached_view: npt.ArrayLike,
        cached_proj: npt.ArrayLike,
        view: npt.ArrayLike,
        proj: npt.ArrayLike,
    ) -> Reprojection | None:
        """The reprojection, or None when a matrix is non-finite or singular."""
        v0, p0, v1, p1 = (
            np.asarray(m, dtype=np.float64) for m in (cached_view, cached_proj, view, proj)
        )
        if any(m.shape != (4, 4) for m in (v0, p0, v1, p1)):
            return None
        inverses = _finite_inverses(np.stack((v0, p0, v1, p1)))
        if inverses is None:
            return None
        v0_inv, p0_inv, v1_inv, p1_inv = inverses
        forward = p1 @ v1 @ v0_inv @ p0_inv
        inverse = p0 @ v0 @ v1_inv @ p1_inv
        z0, z1 = _z_at_infinity(p0_inv), _z_at_infinity(p1_inv)
        if z0 is None or z1 is None or not np.all(np.isfinite(forward)):
            return None
        return Reprojection(forward, inverse, z0, z1)

    def tensor(self, which: str, device: torch.device) -> torch.Tensor:
        m = self.forward if which == "forward" else self.inverse
        return torch.as_tensor(m, dtype=torch.float32, device=device)


def pixel_space_matrices(reproj: Reprojection, w: int, h: int) -> tuple[F64Array, F64Array]:
    """The reprojection on pixel coordinates, for the pixel stage.

    ``F`` takes a cached pixel (u, v, depth, 1) to new clip space; ``G`` takes a
    new pixel (x, y, depth, 1) to cached homogeneous pixels.
    """
    to_ndc = np.array(
        [[2.0 / w, 0, 0, -1.0], [0, -2.0 / h, 0, 1.0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    )
    to_pix = np.array(
        [[w / 2.0, 0, 0, w / 2.0], [0, -h / 2.0, 0, h / 2.0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    )
    return reproj.forward @ to_ndc, to_pix @ reproj.inverse @ to_ndc


def _z_at_infinity(p_inv: F64Array) -> float | None:
    """NDC z where P^-1 (0, 0, z, 1) has w = 0 (independent of x, y for perspective)."""
    a, b = p_inv[3, 2], p_inv[3, 3]
    if abs(a) < 1e-30 or abs(p_inv[3, 0]) > 1e-9 * abs(a) or abs(p_inv[3, 1]) > 1e-9 * abs(a):
        return None  # orthographic or oblique: no single plane at infinity
    return float(-b / a)


def z_at_infinity(proj: npt.ArrayLike) -> float | None:
    """NDC depth of the plane at infinity of one projection, as ``Reprojection.between``
    computes it (None when non-finite, singular, orthographic or oblique)."""
    inverses = _finite_inverses(np.asarray(proj, dtype=np.float64)[None])
    return None if inverses is None else _z_at_infinity(inverses[0])


def sky_as_direction(depth: torch.Tensor, z_inf: float) -> torch.Tensor:
    """Depth with sky (>= 1) replaced by the plane at infinity."""
    return torch.where(depth >= 1.0, torch.full_like(depth, z_inf), depth)


def transform(
    m: torch.Tensor, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``m @ (x, y, z, 1)`` component-wise for same-shape tensors (no (N, 4) temporaries)."""
    r: list[list[float]] = m.tolist()

    def row(i: int) -> torch.Tensor:
        out: torch.Tensor = x * r[i][0] + y * r[i][1] + z * r[i][2] + r[i][3]
        return out

    return row(0), row(1), row(2), row(3)


def pixel_to_ndc(
    px: torch.Tensor, py: torch.Tensor, w: int, h: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous pixel coordinates (centre of pixel i at i + 0.5) -> NDC x, y."""
    return px * (2.0 / w) - 1.0, 1.0 - py * (2.0 / h)


def ndc_to_pixel(
    nx: torch.Tensor, ny: torch.Tensor, w: int, h: int
) -> tuple[torch.Tensor, torch.Tensor]:
    return (nx + 1.0) * (0.5 * w), (1.0 - ny) * (0.5 * h)


@dataclass
class Projected:
    """Points after reprojection: pixel position, NDC depth and whether they are usable."""

    px: torch.Tensor
    py: torch.Tensor
    depth: torch.Tensor
    valid: torch.Tensor  # in front of the new near plane (clip 0 <= z, w > 0)


def reproject_points(
    m: torch.Tensor, px: torch.Tensor, py: torch.Tensor, depth: torch.Tensor, w: int, h: int
) -> Projected:
    """Pixel positions + NDC depths (sky already as z_inf) through ``m``; never NaN/Inf.

    Invalid points (behind the eye or in front of the near plane) get finite
    placeholder values and ``valid`` False; callers drop or mask them.
    """
    nx, ny = pixel_to_ndc(px, py, w, h)
    cx, cy, cz, cw = transform(m, nx, ny, depth)
    valid = (cw > MIN_CLIP_W) & (cz >= 0.0) & torch.isfinite(cx) & torch.isfinite(cy)
    inv_w = torch.where(valid, cw, torch.ones_like(cw)).reciprocal()
    qx, qy = ndc_to_pixel(cx * inv_w, cy * inv_w, w, h)
    lim = 64.0 * float(max(w, h))  # keep far-off screen positions finite and bounded
    qx = torch.where(valid, qx.clamp(-lim, lim), torch.zeros_like(qx))
    qy = torch.where(valid, qy.clamp(-lim, lim), torch.zeros_like(qy))
    qz = torch.where(valid, cz * inv_w, torch.ones_like(cz))
    return Projected(qx, qy, qz, valid)
