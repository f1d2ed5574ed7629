"""What the browser shows against what the session sent: small thumbnails of the
frames the session encoded, by frame id, and the page's canvas snapshots compared
with them (PSNR). Used by the app benchmark and the end-to-end tests."""

from __future__ import annotations

import base64
import io
import threading
import time
from collections import OrderedDict
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

THUMB = 4  # box-downscale factor of the thumbnails
KEEP_FRAMES = 300

Thumb = npt.NDArray[np.float32]


def thumbnail(rgb: npt.NDArray[Any]) -> Thumb:
    """(H, W, 3) -> (H/4, W/4, 3) float32 box average: what the tap keeps and the
    page's snapshot is compared as (encoder noise averages out; a wrong frame does not)."""
    import cv2  # the game extra's; the benches that tap frames need it anyway

    h, w = rgb.shape[0] // THUMB * THUMB, rgb.shape[1] // THUMB * THUMB
    a = np.ascontiguousarray(rgb[:h, :w, :3], dtype=np.float32)
    # OpenCV's area resize at an integer factor is exactly the box mean, in 1.7 ms
    # at 1280x720 where numpy's reshape-mean took 20: the tap runs on the encoding
    # thread for every frame, and the 20 ms had cost the network bench a third of
    # its frame rate.
    small = cv2.resize(a, (w // THUMB, h // THUMB), interpolation=cv2.INTER_AREA)
    thumb: Thumb = np.asarray(small, dtype=np.float32)
    return thumb


def psnr(a: Thumb, b: Thumb) -> float:
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
    session encoded, by frame id, with their arrival times."""

    def __init__(self, keep: int = KEEP_FRAMES) -> None:
        self._keep = keep
        self._lock = threading.Lock()
        self.thumbs: OrderedDict[int, Thumb] = OrderedDict()
        self.times: list[float] = []

    def __call__(self, frame_id: int, color: npt.NDArray[np.uint8]) -> None:
        thumb = thumbnail(color)
        with self._lock:
            self.thumbs[frame_id] = thumb
            while len(self.thumbs) > self._keep:
                self.thumbs.popitem(last=False)
            self.times.append(time.monotonic())

    def get(self, frame_id: int) -> Thumb | None:
        with self._lock:
            return self.thumbs.get(frame_id)

    def items(self) -> list[tuple[int, Thumb]]:
        with self._lock:
            return list(self.thumbs.items())

    def frames_between(self, t0: float, t1: float) -> int:
        with self._lock:
            return sum(1 for t in self.times if t0 <= t < t1)


class ThumbSource(Protocol):
    """Where the session's frames are looked up by id: a FrameThumbs in the same
    process, or a session's frame tap over HTTP (deploy/smoke_check.py)."""

    def get(self, frame_id: int) -> Thumb | None: ...


def snapshot_psnr(page: Any, thumbs: ThumbSource, count: int = 6, gap_ms: int = 150) -> list[float]:
    """PSNR of ``count`` canvas snapshots (``window.upcast.snapshot()``) against the
    session's frame with the same id; snapshots whose frame is unknown are retried."""
    out: list[float] = []
    for _ in range(count * 10):
        snap = page.evaluate("() => window.upcast.snapshot()")
        sent = thumbs.get(snap["frameId"]) if snap["frameId"] is not None else None
        if sent is not None:
            out.append(psnr(thumbnail(decode_data_url(snap["dataUrl"])), sent))
            if len(out) == count:
                return out
        page.wait_for_timeout(gap_ms)
    raise RuntimeError(f"only {len(out)} of {count} snapshots showed a frame the session sent")
