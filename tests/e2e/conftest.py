"""Fixtures for the end-to-end tests: the real stack and headless Chromium.

The stack is started the way ``upcast up`` starts it (server/bench/latency.py
LiveStack: relay process, game and worker processes, the streaming session on
a thread of this process). A frame tap keeps a small thumbnail of each frame the
server encoded, by frame id, so a test can compare what the browser's canvas
shows with what the server sent.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import pytest

from server.bench.latency import LiveStack
from server.ops.browser_paths import WEB_ROOT
from server.serve.snapshots import (
    FrameThumbs,
    Thumb,
    decode_data_url,
    page_thumbnail,
    psnr,
    thumbnail,
)
from server.stack.local import SessionConfig
from tests.chromium import browser_marks

# Re-exported for the tests (thumbnails and PSNR live in server/serve/snapshots.py).
__all__ = ["FrameTap", "Live", "Thumb", "decode_data_url", "page_thumbnail", "psnr", "thumbnail"]

RENDER = "320x180"
DISPLAY = "640x360"
FPS = 30.0
PRESENTED_AT_LEAST = "n => window.upcast && window.upcast.stats().framesPresented >= n"


def needs(page: str) -> list[pytest.MarkDecorator]:
    """Marks for an e2e module that loads ``page`` from the built client."""
    return browser_marks(WEB_ROOT / page)


FrameTap = FrameThumbs  # the name the tests use


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
def start_live(
    scene: str,
    *,
    fps: float = FPS,
    frame_generation: bool = False,
    ladder: tuple[int, ...] = (),
) -> Iterator[Live]:
    """``ladder``: the spectators' rendition ladder divisors (none by default)."""
    tap = FrameTap()
    config = SessionConfig(
        scene=scene,
        render_size=RENDER,
        display_size=DISPLAY,
        fps=fps,
        frame_generation=frame_generation,
    )
    with LiveStack(config, frame_tap=tap, ladder=ladder) as stack:
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
