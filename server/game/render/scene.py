"""A scene: objects, materials, a scripted camera path and its hard cuts."""

from __future__ import annotations

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

    def cut_between(self, prev_t: float, t: float) -> bool:
        """True when a hard cut lies in (prev_t, t] (or [t, prev_t) when going back)."""
        lo, hi = min(prev_t, t), max(prev_t, t)
        return any(lo < c <= hi for c in self.cut_times)
