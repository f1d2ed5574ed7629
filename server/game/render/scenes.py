"""Named scene presets: a registry of factories, each deterministic from a seed.

Every scene is a function of time t in seconds, so the game can run at any
frame rate. The shared world is a grass field with a gravel path, brick
buildings, photo-textured crates, pillars, spheres, a fence and a text sign.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.game.render.camera import CameraPose
from server.game.render.scene import Scene
from server.game.render.shapes import Box, Ground, Material, Pose, Quad, SceneObject, Sphere

MATERIALS: dict[str, Material] = {
    "grass": Material("grass", (0.45, 0.62, 0.3), (3.0, 3.0)),
    "gravel": Material("gravel", (0.75, 0.7, 0.62), (1.5, 1.5)),
    "brick": Material("brick", (0.85, 0.5, 0.4), (2.5, 2.5)),
    "concrete": Material("noise", (0.8, 0.8, 0.78), (2.0, 2.0)),
    "checker": Material("checker", (1.0, 0.95, 0.9), (1.0, 1.0)),
    "stripes": Material("stripes", (0.9, 0.35, 0.25), (1.0, 1.0)),
    "wood": Material("noise", (0.55, 0.36, 0.2), (0.5, 0.5)),
    "coffee": Material("coffee", tile=(1.2, 1.2)),
    "chelsea": Material("chelsea", tile=(1.2, 1.2)),
    "astronaut": Material("astronaut", tile=(1.2, 1.2)),
    "rocket": Material("rocket", tile=(1.2, 1.2)),
    "sign": Material("sign", tile=(4.0, 4.0)),
    "sign_raw": Material("sign", tile=(4.0, 4.0), mip=False),
    "page": Material("page", tile=(3.0, 1.5)),
    "page_raw": Material("page", tile=(3.0, 1.5), mip=False),
    "text_raw": Material("text", tile=(2.6, 1.0), mip=False),
    "white": Material("white", (0.9, 0.9, 0.9)),
}
PHOTOS = ("coffee", "chelsea", "astronaut", "rocket")


def _world(seed: int, *, sign_material: str = "sign", fence: bool = True) -> list[SceneObject]:
    rng = np.random.default_rng(seed)
    still = SceneObject.still
    objs = [
        SceneObject.still(Ground(path_material="gravel"), "grass", (0.0, 0.0, 0.0)),
        still(Box((3.0, 2.5, 3.0)), "brick", (-8.0, 2.5, -14.0), 10.0),
        still(Box((4.0, 3.5, 3.0)), "brick", (9.0, 3.5, -26.0), -15.0),
        still(Box((6.0, 4.5, 2.5)), "concrete", (-3.0, 4.5, -48.0)),
        # The sign board on two posts, facing the path.
        still(Quad(4.0, 4.0), sign_material, (0.0, 1.2, -12.0)),
        still(Box((0.06, 0.6, 0.06)), "wood", (-1.9, 0.6, -12.02)),
        still(Box((0.06, 0.6, 0.06)), "wood", (1.9, 0.6, -12.02)),
        still(Sphere(0.9), "stripes", (4.5, 0.9, -8.0)),
        still(Sphere(0.6), "checker", (-4.0, 0.6, -4.5)),
    ]
    if fence:
        objs.append(still(Quad(20.0, 1.3, fence=True), "wood", (2.6, 0.0, -12.0), 90.0))
    # Photo crates scattered by the seed: the one source of randomness.
    for i in range(4):
        x = float(rng.uniform(-7.0, -2.5))
        z = float(rng.uniform(-10.0, -2.0)) - 2.0 * i
        yaw = float(rng.uniform(0.0, 90.0))
        objs.append(still(Box((0.5, 0.5, 0.5)), PHOTOS[i], (x, 0.5, z), yaw))
    return objs


def _pillars() -> list[SceneObject]:
    """Pillars along both sides of the path at several depths: parallax and disocclusion."""
    out = []
    for k, z in enumerate((-3.0, -7.0, -12.5, -19.0, -27.0)):
        for side in (-1.0, 1.0):
            x = side * (1.9 + 0.3 * (k % 2))
            out.append(SceneObject.still(Box((0.3, 2.0, 0.3)), "concrete", (x, 2.0, z), 15.0 * k))
    return out


def _mover(shape: Box | Sphere, material: str, fn: Callable[[float], Pose]) -> SceneObject:
    return SceneObject(shape, material, fn, moving=True)


def _crossing_objects() -> list[SceneObject]:
    return [
        _mover(
            Box((0.6, 0.6, 0.6)),
            "checker",
            lambda t: Pose((3.5 * math.sin(0.9 * t), 0.6, -6.0), 60.0 * t),
        ),
        _mover(
            Sphere(0.7),
            "stripes",
            lambda t: Pose((4.0 * math.cos(0.6 * t), 0.7, -10.0), -90.0 * t),
        ),
        _mover(
            Box((0.4, 0.9, 0.4)),
            "astronaut",
            lambda t: Pose(
                (-2.0 + 1.5 * math.sin(1.3 * t), 0.9 + 0.4 * abs(math.sin(2.0 * t)), -4.0), 30.0 * t
            ),
        ),
    ]


def _scene(
    name: str,
    objs: list[SceneObject],
    camera: Callable[[float], CameraPose],
    cut_times: tuple[float, ...] = (),
    cut_period: float | None = None,
) -> Scene:
    return Scene(name, tuple(objs), MATERIALS, camera, cut_times=cut_times, cut_period=cut_period)


def static(seed: int) -> Scene:
    pose = CameraPose((0.0, 1.7, 6.0), 0.0, -6.0)
    return _scene("static", _world(seed), lambda _t: pose)


def slow_pan(seed: int) -> Scene:
    return _scene(
        "slow_pan", _world(seed), lambda t: CameraPose((0.0, 1.7, 6.0), 15.0 - 10.0 * t, -5.0)
    )


def fast_yaw(seed: int) -> Scene:
    return _scene("fast_yaw", _world(seed), lambda t: CameraPose((0.0, 1.7, 2.0), -200.0 * t, -3.0))


def dolly(seed: int) -> Scene:
    return _scene(
        "dolly",
        _world(seed) + _pillars(),
        lambda t: CameraPose((0.3, 1.5, 6.0 - 3.0 * t), 0.0, -4.0),
    )


def moving_objects(seed: int) -> Scene:
    pose = CameraPose((0.0, 1.8, 4.0), 0.0, -8.0)
    return _scene("moving_objects", _world(seed) + _crossing_objects(), lambda _t: pose)


CUT_TIME = 1.0


def scene_cut(seed: int) -> Scene:
    def camera(t: float) -> CameraPose:
        if t < CUT_TIME:
            return CameraPose((0.0, 1.7, 6.0 - 1.0 * t), 5.0 * t, -5.0)
        # After the cut: across the field, looking back at the buildings.
        return CameraPose((14.0, 3.0, -36.0), 135.0 + 5.0 * (t - CUT_TIME), -8.0)

    return _scene("scene_cut", _world(seed), camera, cut_times=(CUT_TIME,))


def thin_detail(seed: int) -> Scene:
    objs = _world(seed, sign_material="sign_raw")
    objs += [
        SceneObject.still(Quad(6.0, 3.0), "page_raw", (-5.5, 1.0, -7.0), 35.0),
        SceneObject.still(Quad(2.6, 1.0), "text_raw", (1.2, 0.2, -6.0), -20.0),
    ]
    return _scene(
        "thin_detail",
        objs,
        lambda t: CameraPose((1.0 + 0.3 * t, 1.6, 1.0), 8.0 + 1.0 * t, -3.0),
    )


# The adaptive-quality benchmark's script: a 60 s cycle of 12 s segments, each one
# imitating a scene above, that repeats forever. Every segment starts with a hard cut
# (the wrap back to 0 at 60, 120, ... too) and the fast yaw also cuts to another place
# every 4 s. Cameras and moving objects read the time within the cycle, and each
# camera the time since its segment began, so every cycle shows the same pictures.
SCHEDULE_CYCLE = 60.0
SCHEDULE_SEGMENT = 12.0
SCHEDULE_HOP = 4.0  # the fast-yaw segment's cut to another place
# What each segment imitates, in order.
SCHEDULE_SEGMENTS: tuple[str, ...] = (
    "static",
    "slow_pan",
    "fast_yaw",
    "moving_objects",
    "thin_detail",
)
SCHEDULE_CUTS: tuple[float, ...] = (12.0, 24.0, 28.0, 32.0, 36.0, 48.0, 60.0)
# The fast yaw's places: (position, yaw at the hop's start, pitch).
_FAST_PLACES: tuple[tuple[tuple[float, float, float], float, float], ...] = (
    ((0.0, 1.7, 2.0), 0.0, -3.0),  # fast_yaw's own
    ((-2.0, 2.2, -20.0), 90.0, -4.0),  # behind the sign, between the buildings
    ((10.0, 2.5, -12.0), 200.0, -6.0),  # right of the fence
)
# Where the crossing objects run: behind and left of the still and panning camera,
# and outside the thin-detail drift's view, so only their own segment (and the fast
# yaw's sweep) sees them.
_CROSSING_AT = (-16.0, 0.0, 20.0)


def schedule_segment(t: float) -> str:
    """The scene the schedule's segment at ``t`` imitates."""
    return SCHEDULE_SEGMENTS[_schedule_phase(t)[0]]


def scene_segments(name: str) -> Callable[[float], str] | None:
    """For a scripted scene, what its segment at game time t imitates; None for the rest."""
    return schedule_segment if name == "schedule" else None


def _schedule_phase(t: float) -> tuple[int, float]:
    """(segment index, seconds since the segment began) at ``t``."""
    s = t % SCHEDULE_CYCLE
    i = min(int(s // SCHEDULE_SEGMENT), len(SCHEDULE_SEGMENTS) - 1)
    return i, s - i * SCHEDULE_SEGMENT


def _looping_crossers() -> list[SceneObject]:
    """moving_objects' crossers at ``_CROSSING_AT``, on rates that fit a whole number
    of times into the cycle: they never stop, never jump, and repeat every cycle."""
    ox, _, oz = _CROSSING_AT
    w = 2.0 * math.pi / SCHEDULE_CYCLE  # one turn a cycle

    def cyc(t: float) -> float:
        return t % SCHEDULE_CYCLE

    return [
        _mover(
            Box((0.6, 0.6, 0.6)),
            "checker",
            lambda t: Pose((ox + 3.5 * math.sin(9 * w * cyc(t)), 0.6, oz - 6.0), 60.0 * cyc(t)),
        ),
        _mover(
            Sphere(0.7),
            "stripes",
            lambda t: Pose((ox + 4.0 * math.cos(6 * w * cyc(t)), 0.7, oz - 10.0), -90.0 * cyc(t)),
        ),
        _mover(
            Box((0.4, 0.9, 0.4)),
            "astronaut",
            lambda t: Pose(
                (
                    ox - 2.0 + 1.5 * math.sin(12 * w * cyc(t)),
                    0.9 + 0.4 * abs(math.sin(19 * w * cyc(t))),
                    oz - 4.0,
                ),
                30.0 * cyc(t),
            ),
        ),
    ]


def schedule(seed: int) -> Scene:
    objs = _world(seed)
    objs += [
        SceneObject.still(Quad(6.0, 3.0), "page_raw", (-5.5, 1.0, -7.0), 35.0),
        SceneObject.still(Quad(2.6, 1.0), "text_raw", (1.2, 0.2, -6.0), -20.0),
    ]
    objs += _looping_crossers()
    ox, _, oz = _CROSSING_AT
    still = CameraPose((0.0, 1.7, 6.0), 0.0, -6.0)
    watch = CameraPose((ox, 1.8, oz + 4.0), 0.0, -8.0)

    def camera(t: float) -> CameraPose:
        i, u = _schedule_phase(t)
        if i == 0:
            return still
        if i == 1:
            return CameraPose((0.0, 1.7, 6.0), 15.0 - 10.0 * u, -5.0)
        if i == 2:
            hop = min(int(u // SCHEDULE_HOP), len(_FAST_PLACES) - 1)
            pos, yaw, pitch = _FAST_PLACES[hop]
            return CameraPose(pos, yaw - 200.0 * (u - hop * SCHEDULE_HOP), pitch)
        if i == 3:
            return watch
        return CameraPose((1.0 + 0.3 * u, 1.6, 1.0), 8.0 + 1.0 * u, -3.0)

    return _scene("schedule", objs, camera, SCHEDULE_CUTS, SCHEDULE_CYCLE)


def default(seed: int) -> Scene:
    def camera(t: float) -> CameraPose:
        a = math.radians(-6.0 * t)  # orbit about the sign at 6 deg/s
        cx, cz, r = 0.0, -12.0, 17.0
        pos = (cx + r * math.sin(a), 3.0 + 0.5 * math.sin(0.3 * t), cz + r * math.cos(a))
        return CameraPose(pos, math.degrees(a), -8.0)

    return _scene("default", _world(seed) + _pillars()[4:] + _crossing_objects()[:2], camera)


@dataclass(frozen=True)
class SceneInfo:
    factory: Callable[[int], Scene]
    camera_motion: bool
    moving_objects: bool
    description: str
    # Whether "all" and the default scene lists take it: False for a script that
    # replays the others (it would only repeat them, and change every default run).
    in_all: bool = True


SCENES: dict[str, SceneInfo] = {
    "static": SceneInfo(static, False, False, "still camera over the textured world"),
    "slow_pan": SceneInfo(slow_pan, True, False, "camera yaws at 10 deg/s"),
    "fast_yaw": SceneInfo(fast_yaw, True, False, "camera yaws at 200 deg/s"),
    "dolly": SceneInfo(dolly, True, False, "forward dolly past pillars: parallax, disocclusion"),
    "moving_objects": SceneInfo(moving_objects, False, True, "still camera, objects cross"),
    "scene_cut": SceneInfo(scene_cut, True, False, "hard cut to another place at t = 1 s"),
    "thin_detail": SceneInfo(
        thin_detail, True, False, "fence bars and text that alias, slow drift"
    ),
    "default": SceneInfo(default, True, True, "slow orbit over the world with moving objects"),
    "schedule": SceneInfo(
        schedule,
        True,
        True,
        "60 s benchmark loop of 12 s segments: still, slow pan, fast yaw cutting to another"
        " place every 4 s, crossing objects, thin detail; a hard cut starts each",
        in_all=False,
    ),
}
# Every scene a name can pick.
SCENE_NAMES: tuple[str, ...] = tuple(SCENES)
# What "all" means, and the evaluation's and the training set's default list.
DEFAULT_SCENE_NAMES: tuple[str, ...] = tuple(n for n, info in SCENES.items() if info.in_all)


def parse_scene_list(text: str) -> list[str]:
    """Scene names from "a,b,c" or "all" (``DEFAULT_SCENE_NAMES``: without the schedule);
    SystemExit naming the allowed ones otherwise."""
    scenes = (
        list(DEFAULT_SCENE_NAMES)
        if text == "all"
        else [s.strip() for s in text.split(",") if s.strip()]
    )
    unknown = [s for s in scenes if s not in SCENE_NAMES]
    if unknown or not scenes:
        raise SystemExit(f"unknown scene(s) {unknown}; choose from {', '.join(SCENE_NAMES)}")
    return scenes


def make_scene(name: str, seed: int = 0) -> Scene:
    """The scene ``name`` built from ``seed``; KeyError names the allowed scenes."""
    try:
        info = SCENES[name]
    except KeyError:
        raise KeyError(f"unknown scene {name!r}; choose one of: {', '.join(SCENE_NAMES)}") from None
    return info.factory(seed)
