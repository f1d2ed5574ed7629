"""Scene description: primitives, materials and objects (numpy only, no torch).

Kept free of torch so that scene names and metadata can be listed by the CLI
without paying for the renderer's imports.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.game.render.transforms import F64Array, rigid, rotation_y

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Pose:
    """Rigid transform of an object: rotation about +y, then translation."""

    position: Vec3
    yaw_deg: float = 0.0

    def matrix(self) -> F64Array:
        """Object-local -> world (4x4)."""
        return rigid(rotation_y(math.radians(self.yaw_deg)), np.asarray(self.position, float))


@dataclass(frozen=True)
class Ground:
    """Infinite plane y = 0 in world space, with an optional straight path along z."""

    path_material: str | None = None
    path_half_width: float = 1.5


@dataclass(frozen=True)
class Box:
    """Axis-aligned in its local frame, centred on the local origin."""

    half: Vec3


@dataclass(frozen=True)
class Sphere:
    radius: float


@dataclass(frozen=True)
class Quad:
    """Vertical two-sided rectangle in local z = 0: x in [-w/2, w/2], y in [0, h].

    ``fence`` cuts it into vertical bars and two rails (alpha test), thin on
    purpose: the bars alias at render size, which is what upscalers must cope with.
    """

    width: float
    height: float
    fence: bool = False
    bar_spacing: float = 0.12
    bar_width: float = 0.025
    rail_width: float = 0.04


Shape = Ground | Box | Sphere | Quad


@dataclass(frozen=True)
class Material:
    """A texture (by name, see textures.py) times a linear tint.

    ``tile`` is metres per texture repeat along u and v; ``mip`` False samples
    the full-resolution level only, so fine detail aliases (thin_detail scene).
    """

    texture: str
    tint: Vec3 = (1.0, 1.0, 1.0)
    tile: tuple[float, float] = (2.0, 2.0)
    mip: bool = True


PoseFn = Callable[[float], Pose]


@dataclass(frozen=True)
class SceneObject:
    shape: Shape
    material: str
    pose_at: PoseFn
    # True when pose_at depends on t: drives the dynamic mask and per-object motion.
    moving: bool = False

    @staticmethod
    def still(shape: Shape, material: str, position: Vec3, yaw_deg: float = 0.0) -> SceneObject:
        pose = Pose(position, yaw_deg)
        return SceneObject(shape, material, lambda _t: pose, moving=False)

    def local_bounds(self) -> tuple[F64Array, F64Array] | None:
        """Local-space bounding box (min, max), None for unbounded shapes."""
        s = self.shape
        if isinstance(s, Box):
            h = np.asarray(s.half, float)
            return -h, h
        if isinstance(s, Sphere):
            r = np.full(3, s.radius)
            return -r, r
        if isinstance(s, Quad):
            return np.array([-s.width / 2, 0.0, 0.0]), np.array([s.width / 2, s.height, 0.0])
        return None
