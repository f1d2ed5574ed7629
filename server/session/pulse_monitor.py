"""The application's sound (source x11): its session's PulseAudio sink, recorded.

``parec`` (pulseaudio-utils) records the null sink's monitor as raw float32 mono at
48 kHz; a reader thread keeps what it gets; the audio capture thread takes samples
at the clock's pace through ``render`` (the SoundSource interface), so the sound sits
on the same media clock as the video. What the capture thread asks for and the
recorder has not delivered yet plays as silence; what piles up beyond MAX_QUEUE_MS
(a stall) is dropped from the front, so the sound never lags by more than that.
The recorder is started again if it ends (the game process restarted its server).
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import threading
from collections import deque
from pathlib import Path

import numpy as np
import numpy.typing as npt

from server.frames.frame import FrameMeta

log = logging.getLogger(__name__)

SAMPLE_RATE = 48_000
MONITOR = "upcast.monitor"
MAX_QUEUE_MS = 80
READ_BYTES = 4 * SAMPLE_RATE // 200  # 5 ms of float32 mono per read
F32Array = npt.NDArray[np.float32]


class PulseMonitor:
    """A SoundSource that plays what the session's PulseAudio sink plays."""

    sample_rate = SAMPLE_RATE

    def __init__(self, socket: Path) -> None:
        self.socket = socket
        self._queue: deque[F32Array] = deque()
        self._queued = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._process: subprocess.Popen[bytes] | None = None
        self.received = 0  # samples recorded
        self.silent = 0  # samples asked for before they were recorded (played as silence)
        self.dropped = 0  # samples dropped from a pile-up
        self._exe = shutil.which("parec")
        if self._exe is None:
            log.warning("parec is missing (Debian: pulseaudio-utils): the application is silent")
            return
        self._thread = threading.Thread(target=self._record, name="pulse-monitor", daemon=True)
        self._thread.start()

    def _record(self) -> None:
        assert self._exe is not None
        while not self._stop.is_set():
            if not self.socket.exists():
                self._stop.wait(0.2)
                continue
            args = [
                self._exe, f"--server=unix:{self.socket}", f"--device={MONITOR}", "--raw",
                "--format=float32le", f"--rate={SAMPLE_RATE}", "--channels=1",
                "--latency-msec=10",
            ]  # fmt: skip
            self._process = subprocess.Popen(
                args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
            )
            stdout = self._process.stdout
            assert stdout is not None
            log.info("sound: recording %s of %s", MONITOR, self.socket)
            pending = b""
            while not self._stop.is_set():
                data = stdout.read1(READ_BYTES)  # type: ignore[attr-defined]
                if not data:
                    break
                pending += data
                whole = len(pending) // 4 * 4
                if whole:
                    self._push(np.frombuffer(pending[:whole], np.float32).copy())
                    pending = pending[whole:]
            self._process.kill()
            self._process.wait()
            if not self._stop.is_set():
                log.info("sound: the recorder ended; starting it again")
                self._stop.wait(0.5)

    def _push(self, samples: F32Array) -> None:
        limit = SAMPLE_RATE * MAX_QUEUE_MS // 1000
        with self._lock:
            self._queue.append(samples)
            self._queued += samples.size
            self.received += samples.size
            while self._queued > limit and self._queue:
                first = self._queue[0]
                excess = self._queued - limit
                if first.size <= excess:
                    self._queue.popleft()
                    self._queued -= first.size
                    self.dropped += first.size
                else:
                    self._queue[0] = first[excess:]
                    self._queued -= excess
                    self.dropped += excess

    # -- SoundSource ------------------------------------------------------------------

    def render(self, n: int) -> F32Array:
        out = np.zeros(n, np.float32)
        filled = 0
        with self._lock:
            while filled < n and self._queue:
                first = self._queue[0]
                take = min(n - filled, first.size)
                out[filled : filled + take] = first[:take]
                filled += take
                if take == first.size:
                    self._queue.popleft()
                else:
                    self._queue[0] = first[take:]
                self._queued -= take
        self.silent += n - filled
        # A level over 1 from a loud program would wrap in Opus' float path: clip.
        np.clip(out, -1.0, 1.0, out=out)
        return out

    def frame(self, meta: FrameMeta) -> None:
        pass  # the program makes its own sound

    def click(self) -> None:
        pass

    def close(self) -> None:
        self._stop.set()
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
