"""Frame generation end to end: the game renders every other frame, the page shows all.

The stack runs as in test_stream_e2e (320x180 -> 640x360) at 30 fps of game
logic with frame generation on, so the game renders 15 frames a second and
the worker predicts the other 15. What is checked in headless Chromium: the
page presents at the server's rate, about half of what it presents was
predicted (the timing track says which), so it shows about twice the rate
the game rendered at; and a predicted frame on the canvas is the frame the
server encoded under that id.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest

from tests.e2e.conftest import FPS, Live, open_player, start_live, stats
from tests.e2e.test_stream_e2e import needs

pytestmark = [*needs("index.html"), pytest.mark.timeout(300)]

PLAY_S = 8.0
# The worker compiles MPE's numba kernels on a thread at start (about 18 s on a quiet
# machine with an empty cache, as on a fresh checkout; longer under load): until then
# predicted ticks are skipped, so the measurement starts once predictions flow.
WARM_UP_S = 180.0


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    with start_live("default", frame_generation=True) as live:
        yield live


def test_the_page_shows_twice_the_rendered_rate(live: Live, browser: Any) -> None:
    page = open_player(browser, live.player_url(), frames=20)
    try:
        page.wait_for_function(
            "() => window.upcast.stats().predictedShare >= 0.4", timeout=WARM_UP_S * 1000
        )
        t0 = time.monotonic()
        first = stats(page)["framesPresented"]
        page.wait_for_timeout(PLAY_S * 1000)
        last = stats(page)
        t1 = time.monotonic()
    finally:
        page.close()
    live.stack.check()
    page_fps = (last["framesPresented"] - first) / (t1 - t0)
    server_fps = live.tap.frames_between(t0, t1) / (t1 - t0)
    share = last["predictedShare"]
    rendered_fps = page_fps * (1.0 - share)
    print(
        f"page {page_fps:.1f} fps, server {server_fps:.1f} fps (logic {FPS:g}), "
        f"predicted {share:.0%}, rendered {rendered_fps:.1f} fps"
    )
    assert last["errors"] == []
    assert page_fps >= 0.9 * server_fps, (page_fps, server_fps)
    # Every other tick is predicted: the page shows about twice what the game rendered.
    assert 0.4 <= share <= 0.55, share
    assert page_fps >= 1.8 * rendered_fps, (page_fps, rendered_fps)
