"""Game sound -> Opus packets on the video's media clock, on a thread of its own.

The media clock: a packet's ``pts_us`` is (monotonic time of its first sample -
``origin_ns``) / 1000, the same origin and clock the capture thread gives the video
(a frame's pts is its ``render_start``). So a sound and the picture of the moment it
belongs to carry the same timestamp, and the player lines them up.

Samples are made up to the monotonic clock minus ``HOLD_BACK_NS``, with the game
state known at that moment. Why not wait for the frames that show that moment: a
frame reaches the session only after render, upscale and two ring handoffs (about
90 ms on 2 cores), and a sound made that late arrives after its picture, which the
player shows at once: sync would be lost. A real game mixes its sound at logic time,
ahead of its frames; doing the same here, a frame's events (a footstep, a scene cut)
sound at their render_start when that sample is still to be made and at once
otherwise (``late_events``, their lateness in ``event_lag_ns``): events lag their
pictures by the pipeline's latency, the sound as a whole is in sync. Sample time is
derived from the clock, never counted on its own, so the audio cannot drift from the
video however long it runs. A source that pauses (``paused``) makes no packets; when it
resumes, its packets carry the clock's time again: the gap is a gap in pts, not a shift.

Nothing here waits on the video: a failed encoder logs once, drops audio for good
and the thread ends; video goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from server.frames.frame import FrameMeta
from server.frames.timing import Stage
from server.game.sounds import SoundSource
from server.media.audio_encode import AudioPacket, OpusEncoder

log = logging.getLogger(__name__)

# Sound is made up to this far behind the clock. None: the synthesiser needs no slack
# (a capture device would: its buffer's latency).
HOLD_BACK_NS = 0
WAKE_S = 0.005  # the thread's tick when nothing happens: half a frame


@dataclass(frozen=True)
class AudioStamps:
    """Wall-clock microseconds of one packet's stages (the timing track's audio record)."""

    sample: int  # when its first sample happens in the game (origin + pts)
    capture: int  # when its samples were synthesised
    encode_start: int
    encode_end: int


@dataclass(frozen=True)
class CapturedAudio:
    packet: AudioPacket
    stamps: AudioStamps
    discontinuity: bool  # pts jumped (the source paused): a new group, the player resyncs


@dataclass
class AudioStats:
    frames: int = 0
    packets: int = 0
    bytes: int = 0
    gaps: int = 0  # times the source paused and resumed
    late_events: int = 0  # frame events that came after their time was already made
    # How late the last late events were (ns), newest last: what a sound lags its picture.
    event_lag_ns: deque[int] = field(default_factory=lambda: deque(maxlen=600))
    encode_ns: int = 0  # CPU time spent synthesising and encoding (thread time)
    failed: bool = False


@dataclass
class _Clock:
    monotonic_ns: Callable[[], int] = time.monotonic_ns
    wall_ns: Callable[[], int] = time.time_ns
    wait: Callable[[float], None] | None = None  # how the thread sleeps (a fake clock's)


@dataclass
class AudioCapture:
    """Synthesises ``source`` on the media clock and hands packets to ``deliver``.

    ``frame``/``click`` are called from any thread; ``step`` does one round of work and
    is what the thread runs (tests call it directly with a fake clock)."""

    source: SoundSource
    encoder: OpusEncoder
    deliver: Callable[[CapturedAudio], None]
    origin_ns: int
    clock: _Clock = field(default_factory=_Clock)
    stats: AudioStats = field(default_factory=AudioStats)
    paused: bool = False  # True: the source produces nothing (a stopped application)

    def __post_init__(self) -> None:
        self._events: queue.SimpleQueue[tuple[int, FrameMeta | None]] = queue.SimpleQueue()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="audio-capture", daemon=True)
        frame = self.encoder.config.frame_samples
        self._rate = self.encoder.config.sample_rate
        self._frame = frame
        # The next sample to make, in samples since origin; None until the first step.
        self._next: int | None = None
        self._pending = np.zeros(0, dtype=np.float32)
        self._pending_start = 0
        self._discontinuity = False

    # -- from other threads ----------------------------------------------------------

    def frame(self, meta: FrameMeta) -> None:
        """A video frame reached the session: its events sound at its render_start."""
        at = int(meta.stamps[Stage.RENDER_START, 0]) or self.clock.monotonic_ns()
        self._events.put((at, meta))
        self._wake.set()

    def click(self) -> None:
        """The viewer used a control (a click sound, now)."""
        self._events.put((self.clock.monotonic_ns(), None))
        self._wake.set()

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(2.0)

    # -- the thread --------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set() and not self.stats.failed:
            self._wake.wait(WAKE_S)
            self._wake.clear()
            self.step()

    def _sample_at(self, monotonic_ns: int) -> int:
        return (monotonic_ns - self.origin_ns) * self._rate // 1_000_000_000

    def step(self) -> None:
        """Make and encode every sample the game is known up to now."""
        if self.stats.failed:
            return
        cpu = time.thread_time_ns()
        now = self.clock.monotonic_ns()
        horizon = self._sample_at(now - HOLD_BACK_NS)
        events: list[tuple[int, FrameMeta | None]] = []
        while True:
            try:
                events.append(self._events.get_nowait())
            except queue.Empty:
                break
        if self._next is None:
            self._next = max(0, horizon)
            self._pending_start = self._next
        for at, meta in sorted(events, key=lambda e: e[0]):
            sample = self._sample_at(at)
            if sample < self._next:
                self.stats.late_events += 1
                lag = (self._next - sample) * 1_000_000_000 // self._rate
                self.stats.event_lag_ns.append(lag)
            # Sound up to the event's own time, never past the horizon: frames only
            # tell what happened, they do not move the clock.
            self._make_until(min(sample, horizon))
            if meta is None:
                self.source.click()
            else:
                self.source.frame(meta)
        self._make_until(horizon)
        self.stats.encode_ns += time.thread_time_ns() - cpu

    def _make_until(self, sample: int) -> None:
        assert self._next is not None
        n = sample - self._next
        if n <= 0:
            return
        if self.paused:
            # Nothing is played while paused; what was made before still goes out whole
            # (padded with silence) and the next sound starts at the clock's time.
            if self._pending.size:
                self._pending = np.concatenate(
                    [self._pending, np.zeros(self._frame - self._pending.size, np.float32)]
                )
                self._emit_frames()
            self._next = sample
            self._pending_start = sample
            self._discontinuity = True
            return
        made = self.source.render(n)
        if not self._pending.size:
            self._pending_start = self._next
        self._pending = np.concatenate([self._pending, made])
        self._next = sample
        self._emit_frames()

    def _emit_frames(self) -> None:
        wall_now = self.clock.wall_ns()
        mono_now = self.clock.monotonic_ns()
        while self._pending.size >= self._frame:
            samples, self._pending = self._pending[: self._frame], self._pending[self._frame :]
            start = self._pending_start
            self._pending_start += self._frame
            self._encode(samples, start, wall_now, mono_now)

    def _encode(self, samples: npt.NDArray[np.float32], start: int, wall: int, mono: int) -> None:
        sample_mono = self.origin_ns + start * 1_000_000_000 // self._rate
        encode_start = self.clock.wall_ns()
        try:
            packets = self.encoder.encode(samples, start)
        except Exception:
            self.stats.failed = True
            log.exception("audio encoder failed: audio is off for this session, video goes on")
            return
        encode_end = self.clock.wall_ns()
        self.stats.frames += 1
        for packet in packets:
            stamps = AudioStamps(
                sample=(wall - (mono - sample_mono)) // 1000,
                capture=wall // 1000,
                encode_start=encode_start // 1000,
                encode_end=encode_end // 1000,
            )
            self.stats.packets += 1
            self.stats.bytes += len(packet.payload)
            if self._discontinuity:
                self.stats.gaps += 1
            self.deliver(CapturedAudio(packet, stamps, self._discontinuity))
            self._discontinuity = False
