"""The rendition ladder's encoder thread: the rungs never delay the player's track.

The capture thread encodes the player's track and hands each frame here: the YUV
frame the player's encoder converted when it is at the display size (no second
conversion), else a copy of the RGB frame (the ring slot is released right after).
Only the newest frame waits: when the rungs fall behind (a loaded host), they skip
frames rather than lag, as the player's track does; a skipped frame's "the player's
track made an IDR" mark carries over to the next one, so the rungs' groups stay
aligned with the player's at the first frame they share.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from av.video.frame import VideoFrame

from server.media.ladder import RenditionLadder, RungFrame

log = logging.getLogger(__name__)

WAIT_S = 0.2


@dataclass
class _Pending:
    frame: npt.NDArray[np.uint8] | VideoFrame
    frame_id: int
    pts_us: int
    align: bool


@dataclass
class LadderThreadStats:
    submitted: int = 0
    encoded: int = 0
    skipped: int = 0  # replaced by a newer frame before the rungs got to them
    errors: int = 0


class LadderThread:
    def __init__(
        self,
        ladder: RenditionLadder,
        deliver: Callable[[list[RungFrame], list[str]], None],
    ) -> None:
        """``deliver(frames, failed_tracks)`` runs on this thread after each frame."""
        self.ladder = ladder
        self.stats = LadderThreadStats()
        self._deliver = deliver
        self._pending: _Pending | None = None
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="ladder-encode", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(5.0)

    def submit(
        self,
        rgb: npt.NDArray[np.uint8],
        yuv: VideoFrame | None,
        frame_id: int,
        pts_us: int,
        align: bool,
    ) -> None:
        """Queue the frame: ``yuv`` (the player's encoder's converted frame at the
        display size, which nothing writes again) when given, else a copy of ``rgb`` (a
        view of the ring, reused after this call)."""
        if self.ladder.idle:
            return  # no rung is watched: not even the copy
        copy: npt.NDArray[np.uint8] | VideoFrame = (
            yuv if yuv is not None else np.array(rgb, copy=True)
        )
        with self._cond:
            old = self._pending
            if old is not None:
                self.stats.skipped += 1
                align = align or old.align
            self._pending = _Pending(copy, frame_id, pts_us, align)
            self.stats.submitted += 1
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stop:
                    self._cond.wait(WAIT_S)
                if self._stop:
                    return
                item = self._pending
                self._pending = None
            assert item is not None
            try:
                frames, failed = self.ladder.encode(
                    item.frame, item.frame_id, item.pts_us, align=item.align
                )
                self.stats.encoded += 1
                self._deliver(frames, failed)
            except Exception:
                self.stats.errors += 1
                log.exception("ladder: frame skipped")
