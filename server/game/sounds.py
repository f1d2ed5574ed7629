"""The reference game's sound: numpy synthesis that follows what happens on screen.

The game state a listener can hear is the state a viewer sees, so the synthesiser is
driven by the frames' own headers (camera, flags) and by the viewer's controls:

- a soft tone per scene: its pitch changes at every scene cut (``FrameFlags.RESET``),
  gliding over a few milliseconds so a cut never clicks;
- footsteps while the camera moves: one short low thump per ``STEP_M`` metres travelled,
  distance read from the camera positions of the frames;
- a click when the viewer uses a control (upscaler, scale, frame generation...).

``render(n)`` returns the next ``n`` mono float32 samples in [-1, 1]. Events are applied
by the caller between renders at the sample they belong to, so the sound of frame N
starts at frame N's time on the shared media clock (server/session/audio_capture.py).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import numpy.typing as npt

from server.frames.frame import FrameFlags, FrameMeta

F32Array = npt.NDArray[np.float32]

SAMPLE_RATE = 48_000
STEP_M = 0.6  # metres of camera travel per footstep
# A teleport (cut, respawn) is not walking: no footsteps for moves longer than this.
MAX_WALK_M = 3.0
# One pitch per scene, cycling: an A minor pentatonic, pleasant and easy to tell apart.
SCENE_TONES_HZ = (220.0, 261.63, 293.66, 329.63, 392.0)
TONE_LEVEL = 0.06
STEP_LEVEL = 0.35
CLICK_LEVEL = 0.3
GLIDE_S = 0.01


class SoundSource(Protocol):
    """What the audio capture thread plays: a sample generator and game events."""

    sample_rate: int

    def render(self, n: int) -> F32Array: ...

    def frame(self, meta: FrameMeta) -> None: ...

    def click(self) -> None: ...


def camera_position(view: npt.NDArray[np.float32]) -> npt.NDArray[np.float64]:
    """World position of a world->view matrix: -R^T t."""
    rotation = view[:3, :3].astype(np.float64)
    return -(rotation.T @ view[:3, 3].astype(np.float64))


def _burst(sample_rate: int, seconds: float, hz: float, decay_s: float) -> F32Array:
    t = np.arange(int(seconds * sample_rate), dtype=np.float64) / sample_rate
    out = np.sin(2 * math.pi * hz * t) * np.exp(-t / decay_s)
    return out.astype(np.float32)


class GameSounds:
    """The reference game's mix; one instance per session, used from one thread."""

    def __init__(self, sample_rate: int = SAMPLE_RATE, seed: int = 0) -> None:
        self.sample_rate = sample_rate
        self.scene = -1  # index into SCENE_TONES_HZ; the first frame seen makes it 0
        self.steps = 0
        self.clicks = 0
        self._phase = 0.0
        self._hz = SCENE_TONES_HZ[0]
        self._target_hz = self._hz
        self._walked_m = 0.0
        self._last: tuple[int, npt.NDArray[np.float64]] | None = None  # frame id, position
        rng = np.random.default_rng(seed)
        # Footstep: a 70 Hz thump with a little noise for the scuff; click: a 2 kHz tick.
        step = _burst(sample_rate, 0.12, 70.0, 0.03)
        noise = rng.standard_normal(step.size).astype(np.float32)
        noise *= np.exp(-np.arange(step.size, dtype=np.float32) / (0.01 * sample_rate))
        self._step = (STEP_LEVEL * (step + 0.15 * noise)).astype(np.float32)
        self._click = (CLICK_LEVEL * _burst(sample_rate, 0.012, 2000.0, 0.002)).astype(np.float32)
        # One-shots still sounding: (samples, how many already played).
        self._voices: list[tuple[F32Array, int]] = []

    def frame(self, meta: FrameMeta) -> None:
        """What frame ``meta`` shows: a scene cut changes the tone, travel makes steps.

        The session sees only some frames (it encodes the newest and skips the rest when
        it falls behind), so distances are measured from the last frame seen, and a cut
        is also a jump too long to walk in the frames between (its RESET frame may be
        one of those skipped). The first frame seen starts the first scene."""
        position = camera_position(meta.camera.view)
        last = self._last
        self._last = meta.frame_id, position
        frames = 1 if last is None else max(1, meta.frame_id - last[0])
        moved = 0.0 if last is None else float(np.linalg.norm(position - last[1]))
        if last is None or meta.flags & FrameFlags.RESET or moved > MAX_WALK_M * frames:
            self.scene += 1
            self._target_hz = SCENE_TONES_HZ[self.scene % len(SCENE_TONES_HZ)]
            self._walked_m = 0.0
            return
        self._walked_m += moved
        if self._walked_m >= STEP_M:
            self._walked_m %= STEP_M
            self.steps += 1
            self._voices.append((self._step, 0))

    def click(self) -> None:
        self.clicks += 1
        self._voices.append((self._click, 0))

    def render(self, n: int) -> F32Array:
        out = self._tone(n)
        still: list[tuple[F32Array, int]] = []
        for samples, played in self._voices:
            take = min(n, samples.size - played)
            out[:take] += samples[played : played + take]
            if played + take < samples.size:
                still.append((samples, played + take))
        self._voices = still
        np.clip(out, -1.0, 1.0, out=out)
        return out

    def _tone(self, n: int) -> F32Array:
        # Phase-continuous, with the frequency gliding to the scene's: no click at a cut.
        glide = 1.0 - math.exp(-1.0 / (GLIDE_S * self.sample_rate))
        hz = np.empty(n, dtype=np.float64)
        current = self._hz
        if abs(self._target_hz - current) < 1e-3:
            hz.fill(self._target_hz)
            current = self._target_hz
        else:
            steps = np.arange(1, n + 1, dtype=np.float64)
            hz[:] = self._target_hz + (current - self._target_hz) * (1.0 - glide) ** steps
            current = float(hz[-1])
        self._hz = current
        phase = self._phase + np.cumsum(2 * math.pi * hz / self.sample_rate)
        self._phase = float(phase[-1] % (2 * math.pi))
        return (TONE_LEVEL * np.sin(phase)).astype(np.float32)


class ToneSource:
    """A pure sine (tests and checks: a known frequency to find at the far end)."""

    def __init__(self, hz: float, level: float = 0.5, sample_rate: int = SAMPLE_RATE) -> None:
        self.sample_rate = sample_rate
        self.hz = hz
        self.level = level
        self.silent = False  # True: zeros (a source gone quiet), the clock goes on
        self._phase = 0.0

    def frame(self, meta: FrameMeta) -> None:
        pass

    def click(self) -> None:
        pass

    def render(self, n: int) -> F32Array:
        if self.silent:
            return np.zeros(n, dtype=np.float32)
        step = 2 * math.pi * self.hz / self.sample_rate
        phase = self._phase + step * np.arange(1, n + 1, dtype=np.float64)
        self._phase = float(phase[-1] % (2 * math.pi))
        return (self.level * np.sin(phase)).astype(np.float32)
