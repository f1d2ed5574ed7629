"""The ``schedule`` scene (the adaptive-quality benchmark's 60 s loop) and periodic cuts."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from server.frames.frame import FrameFlags, Size
from server.game.render.camera import CameraPose
from server.game.render.renderer import Renderer
from server.game.render.scene import Scene
from server.game.render.scenes import (
    DEFAULT_SCENE_NAMES,
    MATERIALS,
    SCENE_NAMES,
    SCENES,
    SCHEDULE_CUTS,
    SCHEDULE_CYCLE,
    SCHEDULE_SEGMENTS,
    make_scene,
    parse_scene_list,
    scene_segments,
    schedule_segment,
)

TINY = Size(64, 36)
FPS = 60.0
# A time inside each segment, and each of the fast yaw's three places.
SEGMENT_TIMES = {
    "static": 6.0,
    "slow_pan": 18.0,
    "fast_yaw": 25.0,
    "moving_objects": 42.0,
    "thin_detail": 54.0,
}
FAST_YAW_PLACES = (25.0, 29.0, 33.0)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_scene("schedule", seed=0)


def _jump(a: CameraPose, b: CameraPose, dt: float) -> bool:
    """More camera change than the schedule's fastest motion (200 deg/s, 0.3 m/s) in dt."""
    travel = math.dist(a.position, b.position)
    return (
        travel > 0.3 * dt + 1e-9
        or abs(a.yaw_deg - b.yaw_deg) > 200.0 * dt + 1e-9
        or abs(a.pitch_deg - b.pitch_deg) > 1e-9
    )


def _same_pose(a: CameraPose, b: CameraPose) -> bool:
    return (
        all(x == pytest.approx(y, abs=1e-9) for x, y in zip(a.position, b.position, strict=True))
        and a.yaw_deg == pytest.approx(b.yaw_deg, abs=1e-9)
        and a.pitch_deg == pytest.approx(b.pitch_deg, abs=1e-9)
    )


def test_registered_by_name_but_not_in_all() -> None:
    info = SCENES["schedule"]
    assert info.camera_motion and info.moving_objects and info.description
    assert "schedule" in SCENE_NAMES
    assert parse_scene_list("static,schedule") == ["static", "schedule"]
    # "all" and the default lists keep the eight content scenes (the schedule replays them).
    assert "schedule" not in DEFAULT_SCENE_NAMES
    assert parse_scene_list("all") == list(DEFAULT_SCENE_NAMES)
    assert set(DEFAULT_SCENE_NAMES) == set(SCENE_NAMES) - {"schedule"}
    assert make_scene("schedule").cut_period == SCHEDULE_CYCLE


def test_segment_names() -> None:
    assert tuple(SEGMENT_TIMES) == SCHEDULE_SEGMENTS
    for cycle in range(3):
        for name, t in SEGMENT_TIMES.items():
            assert schedule_segment(t + cycle * SCHEDULE_CYCLE) == name
    assert schedule_segment(11.999) == "static" and schedule_segment(12.0) == "slow_pan"
    assert schedule_segment(59.999) == "thin_detail" and schedule_segment(60.0) == "static"
    assert scene_segments("schedule") is schedule_segment
    assert scene_segments("static") is None


def test_segment_boundaries_are_cuts(scene: Scene) -> None:
    assert scene.cut_between(11.99, 12.0)
    assert not scene.cut_between(12.0, 12.1)
    assert not scene.cut_between(0.0, 11.99)
    # Every segment boundary and the fast yaw's hops, in the first cycle and later ones.
    for cycle in range(3):
        base = cycle * SCHEDULE_CYCLE
        for c in (12.0, 24.0, 28.0, 32.0, 36.0, 48.0, 60.0):
            assert scene.cut_between(base + c - 0.01, base + c), base + c
            assert not scene.cut_between(base + c, base + c + 0.01), base + c
    # The wrap: 60, 120, ... but not 0 (the first frame is RESET anyway).
    assert scene.cut_between(59.99, 60.0) and scene.cut_between(119.99, 120.0)
    assert scene.cut_between(179.99, 180.0)
    assert not scene.cut_between(-0.01, 0.0) and not scene.cut_between(0.0, 0.01)
    assert not scene.cut_between(60.0, 71.99)
    # Inside the fast yaw, a cut every 4 s only.
    assert not scene.cut_between(24.0, 27.99) and not scene.cut_between(88.01, 91.99)


def test_backward_intervals(scene: Scene) -> None:
    # Same rule both ways: a cut c counts when min(t, prev_t) < c <= max(t, prev_t).
    assert scene.cut_between(12.0, 11.99)
    assert not scene.cut_between(12.1, 12.0)
    assert scene.cut_between(61.0, 59.0)
    assert scene.cut_between(120.0, 119.5)
    assert not scene.cut_between(71.0, 60.0)
    assert scene.cut_between(100.0, 95.0)  # 92 = 32 + 60
    for a, b in ((3.0, 70.0), (11.0, 13.0), (26.0, 30.0), (61.0, 62.0)):
        assert scene.cut_between(a, b) == scene.cut_between(b, a)


def test_interval_longer_than_a_period(scene: Scene) -> None:
    assert scene.cut_between(0.5, 61.0)
    assert scene.cut_between(61.0, 0.5)
    assert scene.cut_between(0.0, 1e6) and scene.cut_between(1e6, 0.0)
    assert scene.cut_between(1.0, 1.0 + SCHEDULE_CYCLE)
    # Before its first cut a scene has none, however long the interval.
    assert not scene.cut_between(-500.0, 11.99)
    one = dataclasses.replace(scene, cut_times=(5.0,), cut_period=10.0)
    assert one.cut_between(5.5, 15.5) and one.cut_between(-100.0, 5.0)
    assert not one.cut_between(-100.0, 4.99)


def _brute_force(cut_times: tuple[float, ...], period: float, a: float, b: float) -> bool:
    lo, hi = min(a, b), max(a, b)
    return any(lo < c + k * period <= hi for c in cut_times for k in range(int(1000 / period) + 2))


def test_periodic_cuts_match_listing_every_repeat() -> None:
    rng = np.random.default_rng(7)
    for cut_times, period in (
        (SCHEDULE_CUTS, SCHEDULE_CYCLE),
        ((0.5, 3.1, 10.0), 7.3),  # a cut time past the first period
        ((0.0,), 2.5),
        ((), 4.0),
    ):
        s = Scene(
            "p", (), MATERIALS, lambda _t: CameraPose((0.0, 0.0, 0.0)), cut_times, cut_period=period
        )
        for _ in range(3000):
            a = float(rng.uniform(-20.0, 600.0))
            b = a + float(rng.choice([-1.0, 1.0])) * float(rng.exponential(period / 2))
            assert s.cut_between(a, b) == _brute_force(cut_times, period, a, b), (a, b)
        # Exactly on repeats: the frame at a cut is after it.
        for c in cut_times:
            for k in range(4):
                at = c + k * period
                assert s.cut_between(at - 1e-6, at) and not s.cut_between(at, at + 1e-6)


def test_cuts_fall_exactly_where_the_camera_jumps(scene: Scene) -> None:
    # Two and a bit cycles of 60 fps frames: a cut between two frames exactly where
    # the camera moved more than its fastest motion allows; continuous everywhere else.
    dt = 1 / FPS
    prev_t, prev = 0.0, scene.camera(0.0)
    cuts = []
    for i in range(1, int(130 * FPS)):
        t = i / FPS
        pose = scene.camera(t)
        cut = scene.cut_between(prev_t, t)
        assert cut == _jump(prev, pose, dt), t
        if cut:
            cuts.append(round(t, 6))
        prev_t, prev = t, pose
    starts = [12.0, 24.0, 28.0, 32.0, 36.0, 48.0, 60.0]
    assert cuts == starts + [c + 60 for c in starts] + [c + 120 for c in starts if c + 120 < 130]


def test_pose_repeats_one_cycle_later(scene: Scene) -> None:
    for t in np.arange(0.0, 60.0, 0.37):
        t = float(t)
        here = scene.camera(t)
        for k in (1, 2, 10):
            assert _same_pose(here, scene.camera(t + k * SCHEDULE_CYCLE)), (t, k)
    # The crossing objects too.
    movers = [o for o in scene.objects if o.moving]
    for t in (1.0, 37.5, 59.9):
        for o in movers:
            a, b = o.pose_at(t), o.pose_at(t + SCHEDULE_CYCLE)
            assert np.allclose(a.position, b.position, atol=1e-9)
            assert np.allclose(a.matrix(), b.matrix(), atol=1e-9)


def test_segments_move_like_the_scenes_they_imitate(scene: Scene) -> None:
    def yaw_rate(t: float) -> float:
        return (scene.camera(t + 0.01).yaw_deg - scene.camera(t).yaw_deg) / 0.01

    assert scene.camera(3.0) == scene.camera(11.0)  # still
    assert yaw_rate(18.0) == pytest.approx(-10.0)
    for t in FAST_YAW_PLACES:
        assert yaw_rate(t) == pytest.approx(-200.0)
    places = {scene.camera(t).position for t in FAST_YAW_PLACES}
    assert len(places) == 3
    assert scene.camera(37.0) == scene.camera(47.0)  # still while objects cross
    drift = math.dist(scene.camera(49.0).position, scene.camera(59.0).position)
    assert 0.0 < drift < 5.0
    # Each segment's camera starts from its segment's start, every cycle.
    assert _same_pose(scene.camera(12.0), scene.camera(72.0))
    assert scene.camera(12.0).yaw_deg == pytest.approx(15.0)


def test_crossing_objects_move_all_the_time(scene: Scene) -> None:
    movers = [o for o in scene.objects if o.moving]
    assert len(movers) == 3
    for t in np.arange(0.0, 120.0, 0.5):
        t = float(t)
        for o in movers:
            assert not np.allclose(o.pose_at(t).matrix(), o.pose_at(t + 0.05).matrix())
    # No jump at the wrap: they are continuous through 60 s.
    for o in movers:
        a, b = o.pose_at(60.0 - 1e-6), o.pose_at(60.0)
        assert np.allclose(a.matrix(), b.matrix(), atol=1e-3)


def test_non_scheduled_scene_keeps_its_one_off_cuts() -> None:
    cut = make_scene("scene_cut")
    assert cut.cut_period is None
    assert cut.cut_between(0.99, 1.0) and cut.cut_between(1.0, 0.99)
    assert not cut.cut_between(1.0, 1.1) and not cut.cut_between(1.1, 1.0)
    assert not cut.cut_between(60.99, 61.0) and not cut.cut_between(2.0, 500.0)
    assert cut.cut_between(0.0, 500.0)
    assert not make_scene("slow_pan").cut_between(0.0, 1e6)
    rng = np.random.default_rng(3)
    cut_times = (0.7, 2.0, 2.0, 9.5)
    s = Scene("n", (), MATERIALS, lambda _t: CameraPose((0.0, 0.0, 0.0)), cut_times)
    for _ in range(2000):
        a, b = (float(x) for x in rng.uniform(-2.0, 12.0, 2))
        lo, hi = min(a, b), max(a, b)
        assert s.cut_between(a, b) == any(lo < c <= hi for c in cut_times)


@pytest.mark.parametrize("period", [0.0, -60.0, math.nan, math.inf, -math.inf])
def test_bad_cut_period_is_refused(scene: Scene, period: float) -> None:
    with pytest.raises(ValueError, match="cut_period"):
        dataclasses.replace(scene, cut_period=period)
    with pytest.raises(ValueError, match="cut_period"):
        Scene("x", (), MATERIALS, lambda _t: CameraPose((0.0, 0.0, 0.0)), cut_period=period)


def test_renders_in_every_segment() -> None:
    r = Renderer("schedule", TINY, jitter=False)
    for name, t in list(SEGMENT_TIMES.items()) + [("fast_yaw", t) for t in FAST_YAW_PLACES]:
        f = r.render(0, t)
        assert f.color.shape == (TINY.height, TINY.width, 3), name
        assert np.isfinite(f.depth).all() and np.isfinite(f.motion).all(), name
        assert f.color.std() > 5.0, name  # a picture, not a flat fill
        seen = bool(f.dynamic_mask.any())
        # The still camera sees no crossing object; its own segment's camera does.
        if name in ("static", "slow_pan", "thin_detail", "moving_objects"):
            assert seen == (name == "moving_objects"), name


def test_rendered_flags_and_pictures_repeat() -> None:
    r = Renderer("schedule", TINY, jitter=False)
    resets = {}
    for i, t in enumerate((11.95, 12.0, 12.05, 59.95, 60.0, 60.05)):
        f = r.render(i + 1, t)
        resets[t] = bool(f.meta.flags & FrameFlags.RESET)
    assert resets == {11.95: True, 12.0: True, 12.05: False, 59.95: True, 60.0: True, 60.05: False}
    # Same seed, same pictures: in another renderer, and one cycle later.
    for t in (40.5, 52.5):
        a = Renderer("schedule", TINY, jitter=False).render(0, t).color.copy()
        b = Renderer("schedule", TINY, jitter=False).render(0, t).color.copy()
        c = Renderer("schedule", TINY, jitter=False).render(0, t + SCHEDULE_CYCLE).color.copy()
        assert np.array_equal(a, b) and np.array_equal(a, c)
