"""The game loop: renders into ring R at its rate, never stalled by a missing worker."""

from __future__ import annotations

import threading
import time

import numpy as np

from server.frames.frame import FrameFlags, Size
from server.frames.ring_frames import create_render_ring, render_frame_of
from server.frames.timing import Stage
from server.game.loop import GameLoop
from server.game.render.camera import CameraInput
from server.game.render.renderer import Renderer

SIZE = Size(96, 54)


def test_game_never_waits_for_an_absent_worker(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)  # real-time: nobody consumes it
    loop = GameLoop(Renderer("default", SIZE), ring, fps=200.0)
    stats = loop.run(threading.Event(), max_frames=12)
    assert stats.frames == 12 and stats.ring_timeouts == 0
    assert ring.counters().dropped_overwritten == 12 - ring.slot_count
    ring.close()


def test_stamps_are_ordered_and_input_moves_camera(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("static", SIZE), ring, fps=60.0)
    assert loop.step(0)
    lease = ring.acquire_read(1.0)
    assert lease is not None
    with lease:
        first = render_frame_of(lease)
        s = first.meta.stamps[:, 0]
        assert 0 < s[Stage.RENDER_START] <= s[Stage.RENDER_END] <= s[Stage.RING_R_READY]
        view_before = first.meta.camera.view.copy()
        assert first.meta.input_seq == 0
    loop.push_input(CameraInput(dyaw_deg=30.0), seq=7)
    assert loop.step(1)
    lease = ring.acquire_read(1.0)
    assert lease is not None
    with lease:
        second = render_frame_of(lease)
        # prev_view of the next frame is the view we saw: the motion vectors are continuous
        assert np.allclose(second.meta.camera.prev_view, view_before, atol=1e-6)
        assert not np.allclose(second.meta.camera.view, view_before, atol=1e-3)
        # the header says which input the frame already shows (input-to-photon latency)
        assert second.meta.input_seq == 7
    ring.close()


def test_scale_change_renders_a_new_size_from_a_reset_frame(ring_name: str) -> None:
    display = Size(192, 108)
    ring = create_render_ring(ring_name, display)
    loop = GameLoop(Renderer("static", SIZE), ring, fps=60.0, display_size=display)
    assert loop.step(0) and loop.step(1)
    loop.request_scale(3.0)
    assert loop.step(2)
    sizes_and_flags = []
    for _ in range(3):
        lease = ring.acquire_read(1.0)
        assert lease is not None
        with lease:
            frame = render_frame_of(lease)
            sizes_and_flags.append((frame.size, bool(frame.meta.flags & FrameFlags.RESET)))
    # Real-time ring of 3 slots: all three frames are still there, oldest first.
    assert sizes_and_flags == [(SIZE, True), (SIZE, False), (Size(64, 36), True)]
    ring.close()


def test_jitter_follows_the_upscaler_kind(ring_name: str) -> None:
    from upscalers import registry

    assert registry.is_temporal("temporal") and not registry.is_temporal("bilinear")
    assert not registry.is_temporal("no_such_method")
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("static", SIZE), ring, fps=60.0)
    jitters = []
    for i, jitter_on in enumerate((True, False, True)):
        loop.request_jitter(jitter_on)
        assert loop.step(i)
        lease = ring.acquire_read(1.0)
        assert lease is not None
        with lease:
            jitters.append(render_frame_of(lease).meta.jitter)
    assert jitters[0] != (0.0, 0.0) and jitters[1] == (0.0, 0.0) and jitters[2] != (0.0, 0.0)
    ring.close()


def test_a_lower_frame_rate_keeps_the_pace_of_game_time(ring_name: str) -> None:
    """The quality controller halves the frame rate: the loop ticks half as often and each
    frame advances game time by the new period, so the world moves as fast as before;
    frame ids stay consecutive (frame generation's base is the id one less)."""
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("default", SIZE), ring, fps=30.0)
    assert [loop.game_time(i) for i in (0, 3)] == [0.0, 0.1]
    assert loop.step(0) and loop.step(1) and loop.step(2)
    loop.request_frame_rate(15.0)
    assert loop.step(3)
    assert loop.frame_rate == 15.0
    # Frame 3 keeps its time (it was scheduled one old period after frame 2); frame 5 is
    # two new periods later.
    assert loop.game_time(3) == 0.1
    assert abs(loop.game_time(5) - (0.1 + 2 / 15)) < 1e-12
    loop.request_frame_rate(float("nan"))  # refused with a log line, nothing changes
    loop.request_frame_rate(-1.0)
    assert loop.step(4) and loop.frame_rate == 15.0
    ring.close()


def test_each_frame_carries_its_game_time_across_a_frame_rate_change(ring_name: str) -> None:
    """The header says when in game time a frame was rendered: after a rate change the
    frame id alone no longer tells it, and a benchmark re-renders the ground truth from it."""
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("default", SIZE), ring, fps=30.0)
    times = []
    for i in range(6):
        if i == 3:
            loop.request_frame_rate(15.0)
        assert loop.step(i)
        lease = ring.acquire_read(1.0)
        assert lease is not None
        with lease:
            times.append(render_frame_of(lease).meta.game_time_us)
    # 0, 1/30, 2/30, then frame 3 keeps its time (3/30) and the period becomes 1/15.
    assert times == [0, 33_333, 66_667, 100_000, 166_667, 233_333]
    assert times[3:] == [round(loop.game_time(i) * 1e6) for i in range(3, 6)]
    ring.close()


def test_the_loop_ticks_at_the_rate_it_is_asked(ring_name: str) -> None:
    ring = create_render_ring(ring_name, SIZE)
    loop = GameLoop(Renderer("static", SIZE), ring, fps=100.0)
    loop.request_frame_rate(20.0)
    start = time.monotonic()
    stats = loop.run(threading.Event(), max_frames=6)
    elapsed = time.monotonic() - start
    # Six frames at 20 fps: five periods of 50 ms between them. At 100 fps it would be
    # 50 ms in all; a loaded machine only makes it longer.
    assert stats.frames == 6
    assert elapsed >= 5 * 0.05 - 0.01
    ring.close()
