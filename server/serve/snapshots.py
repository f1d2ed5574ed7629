"""What the browser shows against what the session sent: small thumbnails of the
frames the session encoded, by frame id, and the page's canvas snapshots compared
with them (PSNR). Used by the app benchmark and the end-to-end tests."""

from __future__ import annotations

import base64
import contextlib
import io
import os
import threading
import time
from collections import OrderedDict, deque
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

THUMB = 4  # box-downscale factor of the thumbnails
KEEP_FRAMES = 300

Thumb = npt.NDArray[np.float32]

# What the canvas shows, as block sums, with the id of the frame it is (one task).
PAGE_THUMBNAIL = "() => window.upcast.thumbnail()"


def thumbnail(rgb: npt.NDArray[Any]) -> Thumb:
    """(H, W, 3 or 4) -> (H/4, W/4, 3) float32 box average: what the tap keeps and the
    page's snapshot is compared as (encoder noise averages out; a wrong frame does not)."""
    import cv2  # the game extra's; the benches that tap frames need it anyway

    h, w = rgb.shape[0] // THUMB * THUMB, rgb.shape[1] // THUMB * THUMB
    # Every channel is converted and resized, the fourth dropped after: converting a
    # strided three-channel view of a 4-channel frame cost 5-7 ms at 1280x720, the
    # contiguous whole 0.7. OpenCV's area resize at an integer factor is exactly the
    # box mean (1.6 ms at 1280x720 where numpy's reshape-mean took 20).
    a = np.ascontiguousarray(rgb[:h, :w], dtype=np.float32)
    small = cv2.resize(a, (w // THUMB, h // THUMB), interpolation=cv2.INTER_AREA)
    thumb: Thumb = np.ascontiguousarray(small[:, :, :3], dtype=np.float32)
    return thumb


def page_thumbnail(result: dict[str, Any]) -> Thumb:
    """The page's own thumbnail (``window.upcast.thumbnail()``: 4x4 box sums of the
    canvas as uint16 in the page's byte order, base64) as ``thumbnail`` gives it: the box mean.
    Reading the canvas back and summing it in the page takes a few milliseconds where a
    PNG snapshot (``toDataURL``) held the page's main thread for tens, often enough to
    show in the glass-to-glass p95 of the benchmark that takes it every second."""
    if result.get("factor") != THUMB:
        raise ValueError(f"page thumbnail factor {result.get('factor')!r}, expected {THUMB}")
    rows, cols = int(result["rows"]), int(result["cols"])
    order = "<" if result.get("littleEndian", True) else ">"
    sums = np.frombuffer(base64.b64decode(result["sums"]), dtype=f"{order}u2")
    if sums.size != rows * cols * 3:
        raise ValueError(f"page thumbnail: {sums.size} sums for {rows}x{cols}x3")
    thumb: Thumb = sums.reshape(rows, cols, 3).astype(np.float32) / np.float32(THUMB * THUMB)
    return thumb


def psnr(a: Thumb, b: Thumb) -> float:
    """PSNR of two thumbnails; of different sizes (the stream encoded below the display
    size: the page decodes the smaller picture), at the smaller one, the larger
    area-averaged down to it: what the smaller picture can show of the larger."""
    if a.shape != b.shape:
        import cv2

        small, large = (a, b) if a.shape[0] * a.shape[1] <= b.shape[0] * b.shape[1] else (b, a)
        size = (small.shape[1], small.shape[0])
        shrunk = cv2.resize(
            np.ascontiguousarray(large, dtype=np.float32), size, interpolation=cv2.INTER_AREA
        )
        a, b = small, np.asarray(shrunk, dtype=np.float32)
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else 10.0 * float(np.log10(255.0**2 / mse))


def decode_data_url(url: str) -> npt.NDArray[np.uint8]:
    from PIL import Image

    header, _, data = url.partition(",")
    if not header.startswith("data:image/"):
        raise ValueError(f"not an image data URL: {header[:40]!r}")
    with Image.open(io.BytesIO(base64.b64decode(data))) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


class FrameThumbs:
    """A frame tap (StreamingSession's ``frame_tap``): thumbnails of the last frames the
    session encoded, by frame id, with their arrival times.

    The tap runs on the encoding thread, so it only copies the frame (well under a
    millisecond at 1280x720); a thread of lower priority makes the thumbnails. Making
    them on the encoding thread cost 2-7 ms a frame there, which the benchmarks that
    use the tap measured as latency. A lookup finishes whatever is still waiting first,
    so what the tap has taken is always found. At most ``MAX_WAITING`` frames wait; past
    that the tap makes the oldest one's thumbnail itself (memory stays bounded)."""

    MAX_WAITING = 8
    IDLE_EXIT_S = 1.0  # the thumbnail thread ends after this long without frames
    KEEP_TIMES = 36_000  # arrival times kept: 20 minutes at 30 fps
    NICE = 10

    def __init__(self, keep: int = KEEP_FRAMES) -> None:
        self._keep = keep
        self._lock = threading.Lock()  # the dicts and lists below
        self._work = threading.Lock()  # one thumbnail made at a time, in order
        self._wake = threading.Event()
        self._waiting: OrderedDict[int, npt.NDArray[np.uint8]] = OrderedDict()
        self._worker: threading.Thread | None = None
        self.thumbs: OrderedDict[int, Thumb] = OrderedDict()
        # Arrival times for frames_between(); bounded, or a long session with a frame
        # tap would keep a float per frame for ever.
        self.times: deque[float] = deque(maxlen=self.KEEP_TIMES)

    def __call__(self, frame_id: int, color: npt.NDArray[np.uint8]) -> None:
        copy = np.array(color, copy=True)  # the view is only valid during the call
        with self._lock:
            self._waiting[frame_id] = copy
            self.times.append(time.monotonic())
            over = len(self._waiting) > self.MAX_WAITING
            if self._worker is None:
                self._worker = threading.Thread(target=self._run, name="frame-thumbs", daemon=True)
                self._worker.start()
        if over:
            with self._work:
                self._make_next()
        self._wake.set()

    def get(self, frame_id: int) -> Thumb | None:
        self._settle()
        with self._lock:
            return self.thumbs.get(frame_id)

    def items(self) -> list[tuple[int, Thumb]]:
        self._settle()
        with self._lock:
            return list(self.thumbs.items())

    def frames_between(self, t0: float, t1: float) -> int:
        """Frames the tap took between two ``time.monotonic()`` readings (within the
        last ``KEEP_TIMES`` frames)."""
        with self._lock:
            return sum(1 for t in self.times if t0 <= t < t1)

    def _make_next(self) -> bool:
        """The oldest waiting frame's thumbnail; the caller holds ``_work``."""
        with self._lock:
            if not self._waiting:
                return False
            frame_id, raw = self._waiting.popitem(last=False)
        thumb = thumbnail(raw)
        with self._lock:
            self.thumbs[frame_id] = thumb
            while len(self.thumbs) > self._keep:
                self.thumbs.popitem(last=False)
        return True

    def _settle(self) -> None:
        with self._work:
            while self._make_next():
                pass

    def _run(self) -> None:
        # Linux sets a thread's nice value by its id; elsewhere it stays as it is.
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.NICE)
        while True:
            woken = self._wake.wait(self.IDLE_EXIT_S)
            self._wake.clear()
            self._settle()
            if not woken:
                with self._lock:
                    if not self._waiting:
                        self._worker = None
                        return


class ThumbSource(Protocol):
    """Where the session's frames are looked up by id: a FrameThumbs in the same
    process, or a session's frame tap over HTTP (deploy/smoke_check.py)."""

    def get(self, frame_id: int) -> Thumb | None: ...


def shown_psnr(page: Any, thumbs: ThumbSource) -> float | None:
    """PSNR of what the canvas shows now against the session's frame with the same id;
    None when the page has shown no frame yet or the session no longer has it."""
    shown = page.evaluate(PAGE_THUMBNAIL)
    frame_id = shown.get("frameId")
    sent = thumbs.get(frame_id) if frame_id is not None else None
    return None if sent is None else psnr(page_thumbnail(shown), sent)


def snapshot_psnr(page: Any, thumbs: ThumbSource, count: int = 6, gap_ms: int = 150) -> list[float]:
    """PSNR of ``count`` canvas thumbnails (``window.upcast.thumbnail()``) against the
    session's frame with the same id; snapshots whose frame is unknown are retried."""
    out: list[float] = []
    for _ in range(count * 10):
        db = shown_psnr(page, thumbs)
        if db is not None:
            out.append(db)
            if len(out) == count:
                return out
        page.wait_for_timeout(gap_ms)
    raise RuntimeError(f"only {len(out)} of {count} snapshots showed a frame the session sent")
