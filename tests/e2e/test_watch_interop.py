"""Interop: the UNMODIFIED ``<moq-watch>`` element of @moq/watch plays our stream.

dist/watch.html (served by ``upcast relay`` next to the player) mounts the stock
element with ``name=game``; it fetches /certificate.sha256, connects over
WebTransport, reads the hang catalog and decodes the CMAF video with
WebCodecs into its canvas. The element has no test hooks, so the test reads the
canvas: it must show the game (a picture close to one of the frames the server
encoded recently) and change over time (the default scene orbits).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from tests.e2e.conftest import Live, decode_data_url, needs, psnr, start_live, thumbnail

pytestmark = [*needs("watch.html"), pytest.mark.timeout(90)]

CANVAS = "document.querySelector('moq-watch canvas')"
# Not a blank or flat canvas: the game's textured world has far more spread than this.
MIN_STD = 20.0
MIN_MATCH_DB = 20.0


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    with start_live("default") as live:
        yield live


def _canvas(page: Any) -> Any:
    url = page.evaluate(f"() => {CANVAS}.toDataURL('image/png')")
    return decode_data_url(url)


def _best_match(live: Live, shown: Any) -> tuple[int, float]:
    """The server frame (of the last few hundred) closest to ``shown``, and its PSNR."""
    scores = [(psnr(shown, thumb), frame_id) for frame_id, thumb in live.tap.items()]
    db, frame_id = max(scores)
    return frame_id, db


def test_moq_watch_element_plays_the_game(live: Live, browser: Any) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 600})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        page.goto(f"http://localhost:{live.port}/watch.html?name=game")
        # The element sizes its canvas to the video once the first frame is drawn.
        page.wait_for_function(f"() => {CANVAS} && {CANVAS}.width === 640", timeout=30_000)
        t0 = time.monotonic()
        shots: list[Any] = []
        while len(shots) < 4:
            page.wait_for_timeout(700)
            shots.append(_canvas(page))
        elapsed = time.monotonic() - t0
        status = page.evaluate("() => document.getElementById('status').dataset.state")
    finally:
        page.close()
    live.stack.check()
    assert errors == []
    assert status == "connected", status
    matches = []
    for shot in shots:
        assert shot.shape == (360, 640, 3)
        assert float(np.std(shot)) >= MIN_STD, "blank or flat canvas"
        matches.append(_best_match(live, thumbnail(shot)))
    print(f"moq-watch canvas over {elapsed:.1f} s: best server match (frame, dB) {matches}")
    # Each picture is one of the frames the game rendered ...
    assert all(db >= MIN_MATCH_DB for _, db in matches), matches
    # ... and it moves on with the game (the default scene orbits).
    ids = [frame_id for frame_id, _ in matches]
    assert ids == sorted(ids) and ids[-1] - ids[0] >= 30, ids
    assert psnr(thumbnail(shots[0]), thumbnail(shots[-1])) < min(db for _, db in matches) - 6.0
