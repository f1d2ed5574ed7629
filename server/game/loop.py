"""The game loop: render at a fixed rate straight into ring R, apply player input.

Game time advances by one period per frame (not by the wall clock), so a run is
deterministic for the same input sequence however the machine keeps up: at a fixed
rate it is ``frame_index / fps``. The loop paces against absolute deadlines; a frame
that starts late is counted and the schedule resyncs instead of rushing to catch up.

The frame rate can change at run time (``request_frame_rate``: the session's quality
controller trades frame rate for CPU when nothing cheaper holds): from the next frame
on the loop ticks at the new rate and each frame advances game time by the new
period, so the game's world keeps its pace and only fewer pictures show it.

Frame generation: ``fps`` stays the rate of game logic and of frames into
ring R, but only every other tick is fully rendered. The tick after a full
render draws only the moving objects (``render_dynamic``, flag PREDICTED) and
the worker predicts the static rest from that full render. A tick renders fully
instead whenever a prediction from the last full render would be wrong or
impossible: no full render on the tick before (first frame, a dropped or failed
one), a scene cut since it, a new render size, or frame generation just
switched on (the worker has nothing cached yet). So a PREDICTED frame's base is
always the frame with id one less, whose camera is its prev camera.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from server.frames.frame import RenderFrame, Size
from server.frames.ring import FrameRing
from server.frames.ring_frames import write_meta
from server.frames.timing import Stage, stamp
from server.game.render.renderer import RenderTargets

log = logging.getLogger(__name__)


class SourceEnded(Exception):
    """Raised by a renderer to end the run for good (a captured application exited,
    its display is gone): the loop stops instead of skipping the frame."""

    def __init__(self, reason: str, code: int = 0) -> None:
        super().__init__(reason)
        self.code = code


class FrameRenderer(Protocol):
    """What the loop needs of a renderer (server.game.render.Renderer is one)."""

    render_size: Size

    def scene_cut_between(self, t0: float, t1: float) -> bool:
        """Whether the picture jumps between game times t0 and t1 (no prediction across)."""
        ...

    def render(
        self, frame_index: int, t: float, targets: RenderTargets | None = None
    ) -> RenderFrame: ...

    def render_dynamic(
        self, frame_index: int, t: float, targets: RenderTargets | None = None
    ) -> RenderFrame: ...

    def apply_input(self, event: Any) -> None: ...

    def set_render_size(self, render_size: Size, scale: float) -> None: ...

    def set_jitter(self, on: bool) -> None: ...


@dataclass
class GameStats:
    frames: int = 0  # into ring R, full or dynamic-only
    frames_rendered: int = 0  # fully rendered
    frames_predicted: int = 0  # only the moving objects drawn; the worker predicts the rest
    late_frames: int = 0
    ring_timeouts: int = 0
    render_errors: int = 0
    inputs_applied: int = 0


class GameLoop:
    def __init__(
        self,
        renderer: FrameRenderer,
        ring: FrameRing,
        fps: float,
        *,
        display_size: Size | None = None,
        frame_generation: bool = False,
    ) -> None:
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        ring.require_fits(*renderer.render_size, what="render size")
        self.renderer = renderer
        self.ring = ring
        self.fps = fps
        # The rate the loop ticks at now (request_frame_rate), and the (frame index,
        # game time) the current rate counts from.
        self.frame_rate = fps
        self._wanted_frame_rate: float | None = None
        self._time_base: tuple[int, float] = (0, 0.0)
        self.stats = GameStats()
        self.ended: SourceEnded | None = None  # why run() stopped early, if it did
        self._inputs: queue.SimpleQueue[tuple[Any, int]] = queue.SimpleQueue()
        self.input_seq = 0  # last applied player input (see FrameMeta.input_seq)
        # The size the worker upscales to; render size = display / scale.
        self.display_size = display_size
        self._wanted_scale: float | None = None
        self._wanted_jitter: bool | None = None
        self.frame_generation = frame_generation
        self._wanted_frame_generation: bool | None = None
        # (frame index, game time) of the last full render: what the worker predicts from.
        self._last_full: tuple[int, float] | None = None
        self._force_full = False
        # Seconds per full render / per dynamic-only draw, for the --metrics-port
        # histograms (server/game/metrics.py).
        self.on_render_time: Callable[[float], None] | None = None
        self.on_dynamic_time: Callable[[float], None] | None = None
        ring.attach_as_producer()

    def push_input(self, event: Any, seq: int = 0) -> None:
        """Queue an input event (thread-safe); applied at the start of the next frame."""
        self._inputs.put((event, seq))

    def request_scale(self, scale: float) -> None:
        """Change the render scale from the next frame on (thread-safe)."""
        if self.display_size is None:
            log.warning("scale change ignored: the game does not know the display size")
            return
        self._wanted_scale = scale

    def request_jitter(self, on: bool) -> None:
        """Turn camera jitter on or off from the next frame on (thread-safe)."""
        self._wanted_jitter = on

    def request_frame_generation(self, on: bool) -> None:
        """Turn frame generation on or off from the next frame on (thread-safe)."""
        self._wanted_frame_generation = on

    def request_frame_rate(self, fps: float) -> None:
        """Tick at ``fps`` from the next frame on (thread-safe); game time keeps its pace."""
        if not (fps > 0 and fps < float("inf")):
            log.warning("frame rate %r ignored: not a positive number", fps)
            return
        self._wanted_frame_rate = fps

    def game_time(self, frame_index: int) -> float:
        """Game time of frame ``frame_index`` at the current rate."""
        base_index, base_t = self._time_base
        return base_t + (frame_index - base_index) / self.frame_rate

    def _apply_frame_rate(self, frame_index: int) -> None:
        fps, self._wanted_frame_rate = self._wanted_frame_rate, None
        if fps is None or fps == self.frame_rate:
            return
        # This frame keeps the time the old rate gave it (it was scheduled one old
        # period after the last); the new period counts from here.
        self._time_base = (frame_index, self.game_time(frame_index))
        self.frame_rate = fps
        log.info("frame rate %.3g fps (configured %.3g)", fps, self.fps)

    def _apply_scale(self) -> None:
        jitter, self._wanted_jitter = self._wanted_jitter, None
        if jitter is not None:
            self.renderer.set_jitter(jitter)
        scale, self._wanted_scale = self._wanted_scale, None
        if scale is None or self.display_size is None:
            return
        w, h = self.display_size
        # Even sizes: the encoder downstream works on 4:2:0 chroma.
        size = Size(max(2, round(w / scale / 2) * 2), max(2, round(h / scale / 2) * 2))
        if size == self.renderer.render_size:
            return
        self.ring.require_fits(*size, what="render size")
        self.renderer.set_render_size(size, scale)
        # A frame of the old size cannot be the base of a prediction at the new one.
        self._force_full = True
        log.info("render scale %.3g: rendering at %s for %s", scale, size, self.display_size)

    def _apply_frame_generation(self) -> None:
        on, self._wanted_frame_generation = self._wanted_frame_generation, None
        if on is None or on == self.frame_generation:
            return
        self.frame_generation = on
        # Switched on: the worker may have cached nothing, so render fully first.
        self._force_full = on
        log.info("frame generation %s", "on" if on else "off")

    def _dynamic_only(self, frame_index: int, t: float) -> bool:
        """Whether this tick may draw only the moving objects (see the module doc)."""
        last = self._last_full
        if not self.frame_generation or self._force_full or last is None:
            return False
        last_index, last_t = last
        return last_index == frame_index - 1 and not self.renderer.scene_cut_between(last_t, t)

    def _drain_inputs(self) -> None:
        while True:
            try:
                event, seq = self._inputs.get_nowait()
            except queue.Empty:
                return
            self.renderer.apply_input(event)
            self.input_seq = max(self.input_seq, seq)
            self.stats.inputs_applied += 1

    def step(self, frame_index: int) -> bool:
        """Render one frame into ring R. False if no slot came in time (frame dropped)."""
        render_start = time.monotonic_ns(), time.time_ns()
        self._apply_frame_rate(frame_index)
        self._apply_scale()
        self._apply_frame_generation()
        self._drain_inputs()
        t = self.game_time(frame_index)
        dynamic_only = self._dynamic_only(frame_index, t)
        # Real-time rings never make the game wait; a lossless ring may, briefly.
        lease = self.ring.acquire_write(timeout_s=1.0 / self.frame_rate)
        if lease is None:
            self.stats.ring_timeouts += 1
            return False
        with lease:
            size = self.renderer.render_size
            # The renderer writes its final planes straight into the slot.
            targets = RenderTargets(**lease.views(size.width, size.height))
            try:
                if dynamic_only:
                    frame = self.renderer.render_dynamic(frame_index, t, targets)
                else:
                    frame = self.renderer.render(frame_index, t, targets)
            except SourceEnded:
                raise
            except Exception:
                self.stats.render_errors += 1
                log.exception("render of frame %d failed; frame skipped", frame_index)
                return False
            meta = frame.meta
            meta.input_seq = self.input_seq
            # The time this tick drew (the frame id alone does not tell it once the
            # frame rate has changed); a predicted tick carries its own time too.
            meta.game_time_us = round(t * 1e6)
            meta.stamps[Stage.RENDER_START] = render_start
            stamp(meta.stamps, Stage.RENDER_END)
            report = self.on_dynamic_time if dynamic_only else self.on_render_time
            if report is not None:
                render_ns = meta.stamps[Stage.RENDER_END, 0] - render_start[0]
                report(float(render_ns) / 1e9)
            write_meta(lease.header, meta)
            lease.commit(stamp_stage=Stage.RING_R_READY)
        self.stats.frames += 1
        if dynamic_only:
            self.stats.frames_predicted += 1
        else:
            self.stats.frames_rendered += 1
            self._last_full = frame_index, t
            self._force_full = False
        return True

    def run(
        self,
        stop: threading.Event,
        *,
        duration_s: float | None = None,
        max_frames: int | None = None,
    ) -> GameStats:
        start = time.monotonic()
        next_deadline = start
        index = 0
        last_report = start
        while not stop.is_set():
            if max_frames is not None and index >= max_frames:
                break
            now = time.monotonic()
            period = 1.0 / self.frame_rate
            if duration_s is not None and now - start >= duration_s:
                break
            if now < next_deadline:
                stop.wait(next_deadline - now)
                if stop.is_set():
                    break
            elif now - next_deadline > period:
                self.stats.late_frames += 1
                next_deadline = now  # resync: never render a burst to catch up
            try:
                self.step(index)
            except SourceEnded as ended:
                log.info("game: the source ended: %s", ended)
                self.ended = ended
                break
            index += 1
            next_deadline += 1.0 / self.frame_rate  # the rate this frame applied
            if now - last_report >= 10.0:
                last_report = now
                log.info("game: %s", self.stats)
        return self.stats
