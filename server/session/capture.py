"""Ring U -> encoder, on a thread of its own (encoding never runs on the event loop).

The thread takes the newest display frame (a viewer wants the present, not a
backlog), encodes it straight from the read-only shared-memory view, releases
the slot and hands the fragment to the asyncio side with
``call_soon_threadsafe``. Waiting on the ring is a futex wait with a timeout,
so a dead worker costs nothing but an idle thread, and the loop notices the
stop flag within one timeout.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from av.video.frame import VideoFrame

from server.frames.frame import FrameMeta
from server.frames.ring import FrameRing
from server.frames.ring_frames import display_frame_of
from server.frames.timing import Stage, stamp
from server.media.encode import EncodedFrame, VideoEncoder

log = logging.getLogger(__name__)

READ_TIMEOUT_S = 0.2

# (display RGB view, the encoder's YUV of it or None, frame id, pts, player IDR)
LadderSink = Callable[[npt.NDArray[np.uint8], VideoFrame | None, int, int, bool], None]


@dataclass
class CaptureStats:
    frames: int = 0
    skipped: int = 0  # frames the worker wrote that we never encoded (newest-only reads)
    thinned: int = 0  # frames left out on purpose: the link cannot carry the full rate
    # Frames whose presentation time is not after the last encoded one's, left out (the
    # encoder needs increasing pts): rendered before the stream's clock origin (the
    # session starts its media clock after the game has already filled the ring), or
    # stamped out of order.
    not_after_last: int = 0
    errors: int = 0


@dataclass(frozen=True)
class CapturedFrame:
    encoded: EncodedFrame
    meta: FrameMeta  # stamps up to encode_end; a copy, safe after the slot is released


class CaptureThread:
    """Consumes ring U, encodes, and delivers each CapturedFrame to ``deliver``."""

    def __init__(
        self,
        ring: FrameRing,
        encoder: VideoEncoder,
        deliver: Callable[[CapturedFrame], None],
        *,
        pts_origin_ns: int | None = None,
        frame_tap: Callable[[int, npt.NDArray[np.uint8]], None] | None = None,
        keep_every: Callable[[], int] | None = None,
        ladder_sink: LadderSink | None = None,
    ) -> None:
        """``frame_tap(frame_id, color)`` sees each encoded frame's pixels (a read-only
        view, valid only during the call): tests compare them with what a browser shows.
        ``keep_every()``: encode one frame in this many (the rate control lowers the
        frame rate when the bitrate alone cannot hold it); read before each frame.
        ``ladder_sink(color, yuv, frame_id, pts_us, player_idr)`` gets every frame,
        thinned ones too (the rendition ladder serves other links than the player's),
        while the slot is held: it must copy what it keeps of ``color``. ``yuv``: the
        encoder's converted frame when it is at the display size, else None."""
        self.ring = ring
        self.encoder = encoder
        self.stats = CaptureStats()
        self._deliver = deliver
        self._stop = threading.Event()
        self._pts_origin_ns = pts_origin_ns
        self._last_seq = 0
        self._frame_tap = frame_tap
        self._keep_every = keep_every
        self._ladder_sink = ladder_sink
        self._counter = 0
        self._last_pts_us: int | None = None
        self._thread = threading.Thread(target=self._run, name="capture-encode", daemon=True)

    def start(self) -> None:
        self.ring.attach_as_consumer()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _pts_us(self, meta: FrameMeta) -> int:
        # Presentation time = when the game started the frame, from the first
        # frame on: predicted and rendered frames interleave correctly and the
        # player's jitter buffer sees the game's real cadence.
        render_start = int(meta.stamps[Stage.RENDER_START, 0]) or time.monotonic_ns()
        if self._pts_origin_ns is None:
            self._pts_origin_ns = render_start
        return max(0, (render_start - self._pts_origin_ns) // 1000)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._step()
            except Exception:
                self.stats.errors += 1
                log.exception("capture: frame skipped")
                self._stop.wait(0.05)  # a persistent fault must not spin a core

    def _step(self) -> None:
        lease = self.ring.acquire_read(READ_TIMEOUT_S, newest=True)
        if lease is None:
            return
        with lease:
            if self._last_seq and lease.seq > self._last_seq + 1:
                self.stats.skipped += lease.seq - self._last_seq - 1
            self._last_seq = lease.seq
            frame = display_frame_of(lease)
            meta = frame.meta  # read_meta copied the header: it outlives the lease
            pts_us = self._pts_us(meta)
            if self._last_pts_us is not None and pts_us <= self._last_pts_us:
                self.stats.not_after_last += 1
                return
            self._last_pts_us = pts_us
            self._counter += 1
            if self._keep_every is not None and self._counter % max(1, self._keep_every()):
                self.stats.thinned += 1
                if self._ladder_sink is not None:
                    self._ladder_sink(frame.color, None, meta.frame_id, pts_us, False)
                return
            stamp(meta.stamps, Stage.ENCODE_START)
            encoded = self.encoder.encode(frame.color, frame_id=meta.frame_id, pts_us=pts_us)
            if self._frame_tap is not None:
                self._frame_tap(meta.frame_id, frame.color)
            if self._ladder_sink is not None:
                yuv = self.encoder.last_yuv
                whole = yuv is not None and (yuv.width, yuv.height) == frame.color.shape[1::-1]
                self._ladder_sink(
                    frame.color, yuv if whole else None, meta.frame_id, pts_us, encoded.keyframe
                )
        stamp(meta.stamps, Stage.ENCODE_END)
        self.stats.frames += 1
        self._deliver(CapturedFrame(encoded, meta))
