"""The game side of frame generation: the dynamic layer and the full/dynamic alternation."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from server.cli import build_parser
from server.frames.frame import FrameFlags, RenderFrame, Size
from server.frames.ring import FrameRing
from server.frames.ring_frames import create_render_ring, render_frame_of
from server.frames.timing import Stage
from server.game.input import InputMessage, InputReceiver, send_input
from server.game.loop import GameLoop
from server.game.metrics import game_registry
from server.game.render.camera import CameraInput
from server.game.render.renderer import Renderer, RenderTargets
from server.game.render.scenes import CUT_TIME

SIZE = Size(96, 54)
F32 = np.float32


# --- Renderer.render_dynamic -------------------------------------------------------------


@pytest.mark.parametrize("scene", ["moving_objects", "default"])
def test_dynamic_layer_is_the_full_render_where_moving_objects_are_seen(scene: str) -> None:
    full_r = Renderer(scene, Size(160, 90), jitter=False)
    dyn_r = Renderer(scene, Size(160, 90), jitter=False)
    seen = hidden = 0
    for i, t in enumerate((0.0, 0.7, 1.9, 3.3)):
        full = full_r.render(i, t)
        dyn = dyn_r.render_dynamic(i, t)
        on = full.dynamic_mask == 1
        # Where the full render sees a moving object, the layer has the same surface:
        # same depth, same colour (no shadows: static objects do not change its lighting).
        assert (dyn.dynamic_mask[on] == 1).all()
        np.testing.assert_allclose(dyn.depth[on], full.depth[on], rtol=0, atol=1e-6)
        diff = np.abs(dyn.color[on].astype(int) - full.color[on].astype(int))
        assert diff.max(initial=0) <= 2
        # Where only the layer has it, static geometry hides it in the full render.
        only_dyn = (dyn.dynamic_mask == 1) & ~on
        assert (dyn.depth[only_dyn] >= full.depth[only_dyn] - 1e-6).all()
        # Elsewhere: nothing drawn.
        off = dyn.dynamic_mask == 0
        assert (dyn.depth[off] == 1.0).all() and (dyn.color[off] == 0).all()
        assert (dyn.motion == 0).all() and set(np.unique(dyn.dynamic_mask)) <= {0, 1}
        seen += int(on.sum())
        hidden += int(only_dyn.sum())
    assert seen > 100  # not vacuous: the objects are on screen
    if scene == "moving_objects":
        assert hidden > 0  # and some pass behind static geometry (crates, sign posts)


def test_dynamic_layer_leaves_the_previous_frame_state_alone() -> None:
    with_layer = Renderer("default", SIZE)
    plain = Renderer("default", SIZE)
    f0 = with_layer.render(0, 0.0)
    plain.render(0, 0.0)
    dyn = with_layer.render_dynamic(1, 0.05)
    # prev camera: the last full render's; camera: this tick's, unjittered.
    cam = dyn.meta.camera
    assert np.array_equal(cam.prev_view, f0.meta.camera.view)
    assert np.array_equal(cam.prev_proj, f0.meta.camera.proj)
    expected_view = with_layer.camera_pose(0.05).view_matrix().astype(F32)
    assert np.array_equal(cam.view, expected_view) and not np.allclose(cam.view, cam.prev_view)
    assert dyn.meta.flags == FrameFlags.PREDICTED
    assert dyn.meta.jitter == (0.0, 0.0) and dyn.meta.frame_id == 1
    # The next full render still moves from frame 0, exactly as if no layer was drawn.
    a = with_layer.render(2, 0.1)
    b = plain.render(2, 0.1)
    assert np.array_equal(a.meta.camera.prev_view, f0.meta.camera.view)
    for name in ("color", "depth", "motion", "dynamic_mask"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.abs(a.motion).max() > 0


def test_dynamic_layer_edge_cases_never_crash() -> None:
    # No full render yet: nothing to predict from, so RESET too and prev = this camera.
    r = Renderer("moving_objects", Size(33, 17))
    first = r.render_dynamic(0, 0.4)
    assert first.meta.flags == FrameFlags.PREDICTED | FrameFlags.RESET
    assert np.array_equal(first.meta.camera.prev_view, first.meta.camera.view)
    assert np.isfinite(first.depth).all() and (first.dynamic_mask == 1).any()
    # A scene without moving objects: an empty layer, written over stale slot contents.
    still = Renderer("static", Size(33, 17))
    targets = RenderTargets.allocate(still.render_size)
    for plane in (targets.color, targets.dynamic_mask):
        plane.fill(7)
    targets.depth.fill(np.nan)
    targets.motion.fill(np.nan)
    empty = still.render_dynamic(3, 1.0, targets)
    assert (empty.color == 0).all() and (empty.dynamic_mask == 0).all()
    assert (empty.depth == 1.0).all() and (empty.motion == 0).all()


# --- GameLoop alternation ----------------------------------------------------------------


@dataclass
class Seen:
    frame_id: int
    flags: FrameFlags
    size: Size
    view: np.ndarray
    prev_view: np.ndarray
    input_seq: int
    game_time_us: int
    stamps: np.ndarray
    mask_pixels: int


def step_and_read(loop: GameLoop, ring: FrameRing, index: int) -> Seen:
    assert loop.step(index)
    lease = ring.acquire_read(1.0)
    assert lease is not None
    with lease:
        f: RenderFrame = render_frame_of(lease)
        cam = f.meta.camera
        return Seen(
            f.meta.frame_id, f.meta.flags, f.size, cam.view.copy(), cam.prev_view.copy(),
            f.meta.input_seq, f.meta.game_time_us, f.meta.stamps.copy(),
            int(f.dynamic_mask.sum()),
        )  # fmt: skip


def predicted(s: Seen) -> bool:
    return bool(s.flags & FrameFlags.PREDICTED)


def test_full_and_dynamic_ticks_alternate_with_the_right_cameras(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    renderer = Renderer("default", SIZE)
    loop = GameLoop(renderer, ring, fps=60.0, frame_generation=True)
    seen = []
    for i in range(8):
        if i == 5:
            loop.push_input(CameraInput(dyaw_deg=20.0), seq=9)
        seen.append(step_and_read(loop, ring, i))
    assert [predicted(s) for s in seen] == [False, True] * 4
    assert [s.frame_id for s in seen] == list(range(8))
    # Dynamic-only ticks carry their own game time, not their base's: the worker's
    # prediction stands for that instant.
    assert [s.game_time_us for s in seen] == [round(i / 60.0 * 1e6) for i in range(8)]
    assert seen[0].flags & FrameFlags.RESET
    for i in range(1, 8, 2):
        dyn, last_full = seen[i], seen[i - 1]
        assert np.array_equal(dyn.prev_view, last_full.view)  # what the worker predicts from
        assert not np.allclose(dyn.view, last_full.view)  # the camera of this tick
        assert dyn.mask_pixels > 0
        s = dyn.stamps[:, 0]
        assert 0 < s[Stage.RENDER_START] <= s[Stage.RENDER_END] <= s[Stage.RING_R_READY]
    # The input applied at tick 5 (dynamic) shows in its camera and header ...
    assert seen[5].input_seq == 9 and seen[4].input_seq == 0
    assert np.allclose(seen[5].view, renderer.camera_pose(5 / 60.0).view_matrix(), atol=1e-5)
    # ... and the next full render's motion spans from the last full render.
    assert np.array_equal(seen[6].prev_view, seen[4].view)
    assert loop.stats.frames == 8
    assert loop.stats.frames_rendered == 4 and loop.stats.frames_predicted == 4


def test_scene_cut_forces_a_full_render(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    fps = 10.0
    cut_tick = round(CUT_TIME * fps)
    loop = GameLoop(Renderer("scene_cut", SIZE), ring, fps=fps, frame_generation=True)
    seen = [step_and_read(loop, ring, i) for i in range(cut_tick - 1, cut_tick + 3)]
    # cut_tick - 1 full (first frame); cut_tick would be dynamic but a cut lies between.
    assert [predicted(s) for s in seen] == [False, False, True, False]
    assert seen[1].flags & FrameFlags.RESET


def test_scale_change_and_switching_on_force_a_full_render(ring_name: str) -> None:
    display = Size(192, 108)
    ring = create_render_ring(ring_name, display)
    loop = GameLoop(Renderer("default", SIZE), ring, fps=60.0, display_size=display)
    kinds = []
    for i in range(10):
        if i == 2:
            loop.request_frame_generation(True)
        if i == 5:
            loop.request_scale(3.0)
        if i == 8:
            loop.request_frame_generation(False)
        s = step_and_read(loop, ring, i)
        kinds.append(("P" if predicted(s) else "F", s.size))
    small = Size(64, 36)
    assert kinds == [
        ("F", SIZE), ("F", SIZE),  # off
        ("F", SIZE), ("P", SIZE), ("F", SIZE),  # switched on: full first
        ("F", small), ("P", small), ("F", small),  # new size: full first
        ("F", small), ("F", small),  # off again
    ]  # fmt: skip
    assert loop.stats.frames_predicted == 2 and loop.stats.frames_rendered == 8


class FailsOnce(Renderer):
    def render(self, frame_index: int, t: float, targets: RenderTargets | None = None,
               **kw: object) -> RenderFrame:  # fmt: skip
        if frame_index == 2:
            raise RuntimeError("injected render failure")
        return super().render(frame_index, t, targets)


def test_a_failed_full_render_is_not_predicted_from(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(FailsOnce("default", SIZE), ring, fps=60.0, frame_generation=True)
    kinds = []
    for i in range(5):
        ok = loop.step(i)
        if not ok:
            kinds.append("-")
            continue
        lease = ring.acquire_read(1.0)
        assert lease is not None
        with lease:
            kinds.append("P" if render_frame_of(lease).meta.flags & FrameFlags.PREDICTED else "F")
    assert kinds == ["F", "P", "-", "F", "P"]
    assert loop.stats.render_errors == 1


def test_metrics_count_full_and_dynamic_frames(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("default", SIZE), ring, fps=200.0, frame_generation=True)
    registry = game_registry(loop)
    loop.run(threading.Event(), max_frames=6)
    value = registry.get_sample_value
    assert value("upcast_game_frames_rendered_total") == 3
    assert value("upcast_game_frames_predicted_total") == 3
    assert value("upcast_game_render_seconds_count") == 3
    assert value("upcast_game_dynamic_draw_seconds_count") == 3


# --- input and command line ---------------------------------------------------------------


def test_frame_generation_input_validates_and_reaches_the_loop(tmp_path: Path) -> None:
    assert InputMessage().frame_generation is None
    assert InputMessage.model_validate_json('{"frame_generation": false}').frame_generation is False
    with pytest.raises(ValidationError):
        InputMessage.model_validate_json('{"frame_generation": "maybe"}')
    got: list[bool] = []
    receiver = InputReceiver(
        tmp_path / "in.sock", lambda _e, _s: None, on_frame_generation=got.append
    )
    try:
        send_input(receiver.path, InputMessage(frame_generation=True))
        send_input(receiver.path, InputMessage(dyaw_deg=1.0))
        send_input(receiver.path, InputMessage(frame_generation=False))
        deadline = time.monotonic() + 3.0
        while receiver.accepted < 3:
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.01)
    finally:
        receiver.close()
    assert got == [True, False]


def test_game_command_frame_generation_flag() -> None:
    parser = build_parser("game")
    assert parser.parse_args(["game", "--ring", "r"]).frame_generation is False
    assert parser.parse_args(["game", "--ring", "r", "--frame-generation"]).frame_generation
    args = parser.parse_args(["game", "--ring", "r", "--no-frame-generation"])
    assert args.frame_generation is False
