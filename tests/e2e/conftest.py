"""Fixtures for the end-to-end tests: the real stack and headless Chromium.

The stack is started the way ``upcast up`` starts it (server/bench/latency.py
LiveStack: relay process, game and worker processes, the streaming session on
a thread of this process). A frame tap keeps a small thumbnail of each frame the
server encoded, by frame id, so a test can compare what the browser's canvas
shows with what the server sent.
"""

from __future__ import annotations

import base64
import contextlib
import io
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from server.bench.latency import LiveStack
from server.ops.browser_paths import WEB_ROOT
from server.stack.local import SessionConfig
from tests.chromium import browser_marks

RENDER = "320x180"
DISPLAY = "640x360"
FPS = 30.0
THUMB = 4  # box-downscale factor of the thumbnails
KEEP_FRAMES = 300
PRESENTED_AT_LEAST = "n => window.upcast && window.upcast.stats().framesPresented >= n"

Thumb = npt.NDArray[np.float32]


def needs(page: str) -> list[pytest.MarkDecorator]:
    """Marks for an e2e module that loads ``page`` from the built client."""
    return browser_marks(WEB_ROOT / page)


def thumbnail(rgb: npt.NDArray[Any]) -> Thumb:
    """(H, W, 3) -> (H/4, W/4, 3) float32 box average (what the tap and the test compare)."""
    h, w = rgb.shape[0] // THUMB * THUMB, rgb.shape[1] // THUMB * THUMB
    a = np.asarray(rgb[:h, :w, :3], dtype=np.float32)
    thumb: Thumb = a.reshape(h // THUMB, THUMB, w // THUMB, THUMB, 3).mean(axis=(1, 3))
    return thumb


def psnr(a: Thumb, b: Thumb) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else 10.0 * float(np.log10(255.0**2 / mse))


def decode_data_url(url: str) -> npt.NDArray[np.uint8]:
    from PIL import Image

    header, _, data = url.partition(",")
    assert header.startswith("data:image/"), header[:40]
    with Image.open(io.BytesIO(base64.b64decode(data))) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


class FrameTap:
    """Thumbnails of the last frames the server encoded, by frame id, with arrival times."""

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


class Live:
    """A running stack, its frame tap and where to watch it."""

    def __init__(self, stack: LiveStack, tap: FrameTap) -> None:
        self.stack = stack
        self.tap = tap

    @property
    def port(self) -> int:
        return self.stack.port

    def player_url(self) -> str:
        return self.stack.player_url(overlay="0")


@contextlib.contextmanager
def start_live(scene: str, *, fps: float = FPS, frame_generation: bool = False) -> Iterator[Live]:
    tap = FrameTap()
    config = SessionConfig(
        scene=scene,
        render_size=RENDER,
        display_size=DISPLAY,
        fps=fps,
        frame_generation=frame_generation,
    )
    with LiveStack(config, frame_tap=tap) as stack:
        yield Live(stack, tap)
        stack.check()


def open_player(browser: Any, url: str, *, frames: int = 5, timeout_s: float = 30.0) -> Any:
    """A new page on ``url`` that has presented ``frames`` frames."""
    page = browser.new_page(viewport={"width": 800, "height": 600})
    page.on("console", lambda m: m.type == "error" and print("page console:", m.text))
    page.goto(url)
    page.wait_for_function(PRESENTED_AT_LEAST, arg=frames, timeout=timeout_s * 1000)
    return page


def stats(page: Any) -> dict[str, Any]:
    return page.evaluate("() => window.upcast.stats()")  # type: ignore[no-any-return]
