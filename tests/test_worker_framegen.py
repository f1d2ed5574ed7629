"""The worker's frame-generation stage: PREDICTED ticks in ring R become presented frames.

The game's dynamic layer for a predicted tick is built here from a full render
of that tick (its dynamic pixels), which is what ``Renderer.render_dynamic``
draws wherever a moving object is visible.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np
import pytest

from server.frames.frame import FrameFlags, FrameMeta, RenderFrame, Size
from server.frames.ring import RingMode
from server.frames.ring_frames import (
    create_display_ring,
    create_render_ring,
    display_frame_of,
    put_render_frame,
)
from server.game.render.renderer import Renderer, RenderTargets
from server.worker.prediction import PredictionStage
from server.worker.upscale import UpscaleWorker
from upscalers.framegen import Prediction
from upscalers.framegen.compose import composite_dynamic
from upscalers.host import UpscalerHost
from upscalers.metrics import psnr
from upscalers.output import to_uint8

RENDER = Size(160, 90)
DISPLAY = Size(320, 180)
FPS = 30.0  # logic rate: full renders at 15, predicted ticks between them


def dynamic_layer(full: RenderFrame, prev_full: RenderFrame) -> RenderFrame:
    """What the game sends for a predicted tick: only the moving objects of ``full``."""
    mask = full.dynamic_mask != 0
    meta = dataclasses.replace(
        full.meta,
        flags=FrameFlags.PREDICTED,
        camera=dataclasses.replace(
            full.meta.camera,
            prev_view=prev_full.meta.camera.view,
            prev_proj=prev_full.meta.camera.proj,
        ),
        stamps=full.meta.stamps.copy(),
    )
    return RenderFrame(
        np.where(mask[..., None], full.color, 0).astype(np.uint8),
        np.where(mask, full.depth, 1.0).astype(np.float32),
        np.zeros_like(full.motion),
        full.dynamic_mask.copy(),
        meta,
    )


def ticks(scene: str, count: int) -> tuple[list[RenderFrame], list[RenderFrame]]:
    """(what the game sends, the full render of every tick for reference)."""
    renderer = Renderer(scene, RENDER, scale=DISPLAY.width / RENDER.width, jitter=False)
    truth: list[RenderFrame] = []
    sent: list[RenderFrame] = []
    last_full_t: float | None = None
    for i in range(count):
        t = i / FPS
        prev = last_full_t if i % 2 == 0 else None
        frame = renderer.render(i, t, RenderTargets.allocate(RENDER), prev_t=prev)
        frame.meta.game_time_us = round(t * 1e6)  # what GameLoop.step stamps
        truth.append(frame)
        if i % 2 == 0:
            sent.append(frame)
            last_full_t = t
        else:
            sent.append(dynamic_layer(frame, truth[i - 1]))
    return sent, truth


class Pipe:
    """Ring R -> UpscaleWorker (in process) -> ring U."""

    def __init__(self, name: str, upscaler: str = "bilinear") -> None:
        self.ring_r = create_render_ring(f"{name}-r", RENDER, mode=RingMode.LOSSLESS, slots=8)
        self.ring_u = create_display_ring(f"{name}-u", DISPLAY, mode=RingMode.LOSSLESS, slots=8)
        self.worker = UpscaleWorker(
            self.ring_r, self.ring_u, UpscalerHost(upscaler, DISPLAY), prediction=PredictionStage()
        )
        self.ring_r.attach_as_producer()
        self.ring_u.attach_as_consumer()

    def run(self, frames: list[RenderFrame]) -> list[tuple[FrameMeta, np.ndarray]]:
        out = []
        for frame in frames:
            assert put_render_frame(self.ring_r, frame, 5.0)
            assert self.worker.process_next(5.0)
            got = self.ring_u.acquire_read(0.0)
            if got is not None:
                with got:
                    shown = display_frame_of(got)
                    out.append((shown.meta, shown.color.copy()))
        return out

    def close(self) -> None:
        for ring in (self.ring_r, self.ring_u):
            ring.unlink()
            ring.close()


@pytest.fixture
def pipe(ring_name: str) -> Iterator[Pipe]:
    p = Pipe(ring_name)
    yield p
    p.close()


def test_predicted_ticks_are_presented_flagged_and_close_to_the_render(pipe: Pipe) -> None:
    sent, truth = ticks("moving_objects", 8)
    shown = pipe.run(sent)
    assert [m.frame_id for m, _ in shown] == list(range(8))
    predicted = [bool(m.flags & FrameFlags.PREDICTED) for m, _ in shown]
    assert predicted == [i % 2 == 1 for i in range(8)]
    # Rendered and predicted frames reach ring U with the game time of the tick they
    # stand for (a benchmark re-renders their ground truth from it).
    assert [m.game_time_us for m, _ in shown] == [round(i / FPS * 1e6) for i in range(8)]
    assert shown[5][0].game_time_us == 166_667
    reference = UpscalerHost("bilinear", DISPLAY)
    for i in range(1, 8, 2):
        want = to_uint8(reference.upscale(truth[i]))
        repeat = to_uint8(reference.upscale(truth[i - 1]))
        got = shown[i][1]
        # The prediction (with the game's moving objects over it) is far closer to what
        # the game would have rendered than showing the last render again.
        assert psnr(want, got) > psnr(want, repeat) + 2.0, i
        assert psnr(want, got) > 35.0, i
    stats = pipe.worker.prediction.stats
    assert (stats.predicted, stats.refused, stats.errors) == (4, 0, 0)
    assert pipe.worker.status()["predicted"] == 4


def test_the_periodic_log_line_gives_the_rate_and_counts_not_the_lists(pipe: Pipe) -> None:
    """The worker's line every 10 s: frame rate over the interval and the counters; the
    list of upscalers (the control API's status has it) repeated each time was noise."""
    sent, _ = ticks("moving_objects", 8)
    pipe.run(sent)
    line = pipe.worker.progress(frames_before=0, interval_s=2.0)
    assert line.startswith("bilinear -> 320x180: 4.0 fps, 8 frames, 0 errors"), line
    assert "predicted 4, refused 0, errors 0" in line
    assert "bicubic" not in line and "[" not in line


def test_a_predicted_tick_before_any_render_is_skipped_not_fatal(pipe: Pipe) -> None:
    sent, _ = ticks("slow_pan", 4)
    shown = pipe.run([sent[1], *sent])
    # The first predicted tick had nothing to predict from; the rest went through.
    assert [m.frame_id for m, _ in shown] == [0, 1, 2, 3]
    assert pipe.worker.prediction.stats.refused == 1


def test_no_prediction_across_a_cut(pipe: Pipe) -> None:
    sent, _ = ticks("slow_pan", 4)
    cut = dataclasses.replace(sent[1].meta, flags=FrameFlags.PREDICTED | FrameFlags.RESET)
    shown = pipe.run([sent[0], dataclasses.replace(sent[1], meta=cut)])
    assert [m.frame_id for m, _ in shown] == [0]
    assert pipe.worker.prediction.stats.refused == 1


def test_temporal_history_never_sees_a_predicted_frame(ring_name: str) -> None:
    sent, _ = ticks("slow_pan", 6)
    p = Pipe(ring_name, upscaler="temporal")
    try:
        shown = p.run(sent)
    finally:
        p.close()
    # Rendered frames come out exactly as if the predicted ticks had never been there.
    alone = UpscalerHost("temporal", DISPLAY)
    for i in (0, 2, 4):
        assert np.array_equal(shown[i][1], to_uint8(alone.upscale(sent[i]))), i
    assert all(bool(m.flags & FrameFlags.PREDICTED) for m, _ in shown[1::2])


def test_composite_depth_tests_the_layer_against_the_prediction() -> None:
    h, w = 4, 5
    pred = Prediction(
        color=np.full((h, w, 3), 10, np.uint8),
        holes=np.zeros((h, w), bool),
        depth=np.full((h, w), 0.5, np.float32),
        source_frame_id=0,
        filled=np.zeros((h, w), bool),
    )
    depth = np.full((h, w), 1.0, np.float32)
    mask = np.zeros((h, w), np.uint8)
    depth[0, 0], mask[0, 0] = 0.4, 1  # in front: drawn
    depth[0, 1], mask[0, 1] = 0.6, 1  # behind the static surface: hidden
    depth[0, 2], mask[0, 2] = np.nan, 1  # corrupt: never punches through
    depth[0, 3] = 0.1  # not in the mask: ignored
    meta = FrameMeta(7, ticks("static", 1)[0][0].meta.camera, (0.0, 0.0), FrameFlags.PREDICTED)
    layer = RenderFrame(
        np.full((h, w, 3), 200, np.uint8), depth, np.zeros((h, w, 2), np.float32), mask, meta
    )
    out = composite_dynamic(pred, layer)
    assert out.color[0, 0, 0] == 200 and out.depth[0, 0] == pytest.approx(0.4)
    assert out.color[0, 1, 0] == 10 and out.depth[0, 1] == pytest.approx(0.5)
    assert out.color[0, 2, 0] == 10 and out.color[0, 3, 0] == 10
    assert out.dynamic_mask.sum() == 1 and out.meta.frame_id == 7
    with pytest.raises(ValueError, match="dynamic layer"):
        composite_dynamic(pred, dataclasses.replace(layer, color=layer.color[:2], depth=depth[:2]))


def test_a_predictor_still_building_skips_ticks_and_never_blocks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import threading

    from upscalers import framegen

    release = threading.Event()
    real_create = framegen.create

    def slow_create(name: str, device: object = None) -> framegen.FramePredictor:
        release.wait(10.0)  # what an empty numba cache looks like: seconds of compiling
        return real_create(name, "cpu")

    monkeypatch.setattr(framegen, "create", slow_create)
    stage = PredictionStage(background=True)
    sent, _ = ticks("slow_pan", 4)
    stage.rendered(sent[0])
    assert stage.predict(sent[1]) is None  # returns at once, the tick is skipped
    assert stage.stats.warming == 1
    release.set()
    assert stage.wait_ready(30.0)
    stage.rendered(sent[2])
    assert stage.predict(sent[3]) is not None
    assert stage.stats.predicted == 1


def test_an_unknown_predictor_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"unknown frame predictor 'nope'; allowed: .*mpe"):
        PredictionStage("nope")


def test_worker_thread_budget_covers_the_compiled_kernels() -> None:
    """``WorkerConfig.threads`` limits numba's kernels too: unlimited, their threads took
    the core the game renders on (22 frames lost in 20 s at 40 fps on 2 cores)."""
    import threading

    import numba

    from server.ops.cpu_threads import limit_compiled_threads

    seen: list[int] = []

    def on_worker_thread() -> None:  # numba's limit is per thread, like a worker's loop
        limit_compiled_threads(1)
        seen.append(numba.get_num_threads())
        limit_compiled_threads(10_000)
        seen.append(numba.get_num_threads())

    t = threading.Thread(target=on_worker_thread)
    t.start()
    t.join()
    assert seen == [1, numba.config.NUMBA_NUM_THREADS]  # type: ignore[attr-defined]
