"""Renderer contract: flags, targets, sizes, jitter, determinism, input, textures, ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from server.frames.frame import FrameFlags, Size
from server.game.render.camera import CameraInput, CameraPose
from server.game.render.renderer import Renderer, RenderTargets
from server.game.render.scenes import CUT_TIME, SCENES
from server.game.render.shading import linear_to_srgb, quantize_into
from server.game.render.shapes import Box, SceneObject
from server.game.render.textures import SKIMAGE_FILES, skimage_data_dir
from server.game.render.transforms import jitter_phase_count

SMALL = Size(160, 90)


def _finite(frame: object) -> None:
    for name in ("depth", "motion"):
        assert np.isfinite(getattr(frame, name)).all(), name


def test_reset_on_first_frame_and_scene_cut() -> None:
    r = Renderer("scene_cut", SMALL)
    flags = []
    for i in range(0, 62):
        f = r.render(i, i / 60.0)
        flags.append(bool(f.meta.flags & FrameFlags.RESET))
        if i == 60:  # t == CUT_TIME: the first frame after the cut
            assert i / 60.0 >= CUT_TIME
            cam = f.meta.camera
            assert np.array_equal(cam.prev_view, cam.view)
            assert np.array_equal(cam.prev_proj, cam.proj)
            assert np.all(f.motion == 0)
    assert flags[0] and flags[60]
    assert not any(flags[1:60]) and not flags[61]


def test_writes_into_given_targets() -> None:
    r = Renderer("moving_objects", SMALL)
    targets = RenderTargets.allocate(SMALL)
    ids = [id(a) for a in (targets.color, targets.depth, targets.motion, targets.dynamic_mask)]
    targets.color[:] = 7
    f = r.render(0, 0.0, targets)
    assert [id(a) for a in (f.color, f.depth, f.motion, f.dynamic_mask)] == ids
    assert f.color is targets.color
    assert not np.all(targets.color == 7)
    assert targets.dynamic_mask.any()


def test_dynamic_mask_only_where_objects_move() -> None:
    moving = Renderer("moving_objects", SMALL).render(0, 0.3)
    still = Renderer("static", SMALL).render(0, 0.3)
    assert moving.dynamic_mask.sum() > 50
    assert set(np.unique(moving.dynamic_mask)) <= {0, 1}
    assert not still.dynamic_mask.any()


@pytest.mark.parametrize(("scale", "phases"), [(1.5, 18), (1.7, 23), (2.0, 32), (3.0, 72)])
def test_jitter_phase_count(scale: float, phases: int) -> None:
    assert jitter_phase_count(scale) == phases
    r = Renderer("static", SMALL, scale=scale)
    assert r.jitter_phases == phases
    jit = {r.jitter_for(i) for i in range(phases)}
    assert len(jit) == phases
    assert r.jitter_for(phases) == r.jitter_for(0)
    assert all(-0.5 <= x < 0.5 and -0.5 <= y < 0.5 for x, y in jit)


@pytest.mark.parametrize("scale", [1.5, 1.7])
def test_odd_size_and_fractional_scale(scale: float) -> None:
    size = Size(641, 359)
    r = Renderer("default", size, scale=scale)
    f0 = r.render(0, 0.0)
    f1 = r.render(1, 1 / 60)
    assert f1.color.shape == (359, 641, 3) and f1.motion.shape == (359, 641, 2)
    _finite(f1)
    assert f0.meta.flags & FrameFlags.RESET and not f1.meta.flags
    display = size.scaled(scale)
    gt = r.render_ground_truth(1 / 60, display, supersample=1)
    assert gt.shape == (display.height, display.width, 3)


def test_deterministic_per_seed() -> None:
    a = Renderer("default", SMALL, seed=3).render(0, 0.4)
    b = Renderer("default", SMALL, seed=3).render(0, 0.4)
    c = Renderer("default", SMALL, seed=4).render(0, 0.4)
    for name in ("color", "depth", "motion", "dynamic_mask"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.color, c.color)


def test_box_straddling_camera_and_near_plane_is_finite() -> None:
    r = Renderer("static", SMALL)
    pose = r.scene.camera(0.0)
    px, py, pz = pose.position
    extra = (
        # The camera is inside this box: only its inner faces are visible.
        SceneObject.still(Box((2.0, 1.0, 0.5)), "brick", (px, py, pz - 0.3)),
        # A box whose front face sits on the near plane.
        SceneObject.still(Box((0.2, 0.2, 0.2)), "checker", (px, py, pz - r.scene.near - 0.2)),
    )
    r.scene = dataclasses.replace(r.scene, objects=r.scene.objects + extra)
    for i in range(3):
        f = r.render(i, i / 60)
        _finite(f)
        assert (f.depth >= 0).all() and (f.depth <= 1).all()
    # Camera inside the box: nothing reaches the sky.
    assert not (f.depth == 1.0).any()


def test_nan_colour_quantizes_to_valid_bytes() -> None:
    lin = torch.rand(4, 5, 3)
    lin[0, 0, 0] = math.nan
    lin[1, 1] = math.inf
    lin[2, 2] = -math.inf
    out = np.full((4, 5, 3), 123, np.uint8)
    quantize_into(linear_to_srgb(lin), torch.from_numpy(out))
    assert out[0, 0, 0] == 0
    assert (out[1, 1] == 255).all() and (out[2, 2] == 0).all()
    ref = np.round(linear_to_srgb(lin[3]).numpy() * 255)
    assert np.array_equal(out[3], ref.astype(np.uint8))


def _input_run(events: list[CameraInput]) -> np.ndarray:
    r = Renderer("static", SMALL)
    for e in events:
        r.apply_input(e)
    return r.render(0, 0.0).meta.camera.view


def test_input_moves_camera_deterministically() -> None:
    base = _input_run([])
    yawed = _input_run([CameraInput(dyaw_deg=30.0)])
    assert not np.allclose(base[:3, :3], yawed[:3, :3])
    fwd = _input_run([CameraInput(forward=2.0)])
    assert np.allclose(base[:3, :3], fwd[:3, :3])
    cam_base = -base[:3, :3].T @ base[:3, 3]
    cam_fwd = -fwd[:3, :3].T @ fwd[:3, 3]
    assert np.allclose(cam_fwd - cam_base, [0.0, 0.0, -2.0], atol=1e-5)
    seq = [CameraInput(10.0, 5.0, 1.0, 0.5, 0.1), CameraInput(-3.0, 100.0, 0.2)]
    assert np.array_equal(_input_run(seq), _input_run(seq))
    # Pitch is clamped to +-85 degrees.
    r = Renderer("static", SMALL)
    r.apply_input(CameraInput(dpitch_deg=500.0))
    assert r.game_camera.state.pitch_deg == pytest.approx(85.0)
    assert r.camera_pose(0.0).pitch_deg <= 85.0


def test_input_between_frames_shows_in_motion() -> None:
    r = Renderer("static", SMALL, jitter=False)
    r.render(0, 0.0)
    r.apply_input(CameraInput(dyaw_deg=2.0))
    f = r.render(1, 1 / 60)
    assert not np.array_equal(f.meta.camera.view, f.meta.camera.prev_view)
    assert np.abs(f.motion[..., 0]).mean() > 1.0


def test_textures_come_from_the_skimage_wheel() -> None:
    folder = skimage_data_dir()
    for fname in SKIMAGE_FILES.values():
        assert (folder / fname).is_file(), fname
    assert "site-packages" in str(folder) or "skimage" in str(folder)


def test_scene_registry_metadata() -> None:
    assert set(SCENES) >= {
        "static",
        "slow_pan",
        "fast_yaw",
        "dolly",
        "moving_objects",
        "scene_cut",
        "thin_detail",
        "default",
    }
    assert not SCENES["static"].camera_motion and SCENES["fast_yaw"].camera_motion
    assert SCENES["moving_objects"].moving_objects
    fy = SCENES["fast_yaw"].factory(0)
    assert abs(fy.camera(1.0).yaw_deg - fy.camera(0.0).yaw_deg) >= 180.0
    assert isinstance(fy.camera(0.0), CameraPose)


def test_ground_truth_supersampling_converges() -> None:
    r = Renderer("thin_detail", SMALL)
    display = Size(240, 135)
    ref = r.render_ground_truth(0.2, display, supersample=6).astype(np.float64)
    gt = r.render_ground_truth(0.2, display, supersample=3).astype(np.float64)
    one = r.render_ground_truth(0.2, display, supersample=1).astype(np.float64)
    assert gt.shape == (135, 240, 3)
    assert np.isfinite(gt).all()
    assert np.mean((gt - ref) ** 2) < np.mean((one - ref) ** 2)


def test_jittered_renders_pick_the_display_mips_unjittered_the_render_mips() -> None:
    # A temporal upscaler gathers the display size's detail over jittered frames; a
    # spatial one would only alias finer mips (FSR/DLSS guides: bias log2(render/display)).
    r = Renderer("static", SMALL, scale=2.0, jitter=True)
    assert r.texture_lod_bias == -1.0
    jittered = r.render(1, 0.0).color.copy()
    r.set_jitter(False)
    assert r.texture_lod_bias == 0.0
    r.set_jitter(True)
    r.set_render_size(Size(120, 68), 4 / 3)  # the player changed the scale
    assert r.texture_lod_bias == pytest.approx(-math.log2(4 / 3))
    fixed = Renderer("static", SMALL, scale=2.0, jitter=True, texture_lod_bias=-1.0)
    assert np.array_equal(fixed.render(1, 0.0).color, jittered)
    r_plain = Renderer("static", SMALL, scale=2.0, jitter=True, texture_lod_bias=0.0)
    assert not np.array_equal(r_plain.render(1, 0.0).color, jittered)


def test_ground_truth_picks_the_display_mips_whatever_the_render_bias() -> None:
    display = Size(96, 54)
    truths = [
        Renderer("static", Size(48, 27), jitter=j, texture_lod_bias=b).render_ground_truth(
            0.1, display, supersample=1
        )
        for j, b in ((True, None), (False, None), (True, 2.0))
    ]
    assert all(np.array_equal(truths[0], t) for t in truths[1:])
