"""A scene: objects, materials, a scripted camera path and its hard cuts."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from server.game.render.camera import CameraPose
from server.game.render.shapes import Material, SceneObject, Vec3

CameraPath = Callable[[float], CameraPose]


@dataclass(frozen=True)
class Lighting:
    """Directional sun plus hemisphere ambient, linear RGB; fog fades to the horizon."""

    sun_direction: Vec3 = (0.45, 0.8, 0.35)  # towards the sun, normalized by the renderer
    sun_color: Vec3 = (1.25, 1.15, 1.0)
    sky_ambient: Vec3 = (0.32, 0.38, 0.5)
    ground_ambient: Vec3 = (0.18, 0.16, 0.13)
    zenith: Vec3 = (0.12, 0.28, 0.65)
    horizon: Vec3 = (0.62, 0.72, 0.85)


@dataclass(frozen=True)
class Scene:
    name: str
    objects: tuple[SceneObject, ...]
    materials: dict[str, Material]
    camera: CameraPath
    # Times at which the camera jumps: the first frame at or after one carries RESET.
    cut_times: tuple[float, ...] = ()
    fov_y_deg: float = 60.0
    near: float = 0.1
    far: float = 200.0
    lighting: Lighting = field(default_factory=Lighting)
    # A scene that loops: every cut c also falls at c + k * cut_period, k = 1, 2, ...
    # (never before c). None: each cut happens once.
    cut_period: float | None = None

    def __post_init__(self) -> None:
        p = self.cut_period
        if p is not None and not (math.isfinite(p) and p > 0.0):
            raise ValueError(f"cut_period must be a positive finite number of seconds, got {p}")

    def cut_between(self, prev_t: float, t: float) -> bool:
        """True when a hard cut c lies in (min, max] of the two times, whichever way time
        went: the frames at prev_t and t sit on different sides of c (a frame at c is
        after it). With ``cut_period`` the cuts repeat; O(len(cut_times)) whatever the
        interval's length."""
        lo, hi = min(prev_t, t), max(prev_t, t)
        period = self.cut_period
        if period is None:
            return any(lo < c <= hi for c in self.cut_times)
        span = hi - lo
        if math.isnan(span):
            return False
        if span >= period:  # a whole period: every cut that has begun repeats inside
            return any(c <= hi for c in self.cut_times)
        for c in self.cut_times:
            if hi < c:
                continue
            # The last repeat at or before hi. The division may round k one off either
            # way: take the largest of k + 1, k, k - 1 whose sum is at or before hi,
            # so the answer agrees with the sums it compares (k = 0 always is).
            k = math.floor((hi - c) / period)
            sums = (c + j * period for j in (k + 1, k, k - 1) if j >= 0)
            last = next((s for s in sums if s <= hi), c)
            if last > lo:
                return True
        return False
