"""Interop: the UNMODIFIED ``<moq-watch>`` element plays the rendition ladder and
switches renditions.

@moq/watch 0.4 picks a rendition of the hang catalog by a target, here the element's
size (its ResizeObserver sets the target to the element's pixels): the largest
rendition that fits, switching tracks when the size changes. With the ladder on (display
640x360: the player's track, ``video.320x180`` and ``video.160x90``), sizing the element
makes it play each rung in turn; the canvas takes the size of the rendition it decodes,
and it keeps showing the game (a picture close to a frame the server encoded).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import Live, decode_data_url, needs, psnr, start_live, thumbnail

pytestmark = [*needs("watch.html"), pytest.mark.timeout(120)]

CANVAS = "document.querySelector('moq-watch canvas')"
ELEMENT = "document.querySelector('moq-watch')"
MIN_MATCH_DB = 18.0


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    with start_live("default", ladder=(2, 4)) as live:
        yield live


def _size_element(page: Any, width: int, height: int) -> None:
    page.evaluate(
        f"() => {{ const e = {ELEMENT}; e.style.width = '{width}px';"
        f" e.style.height = '{height}px'; }}"
    )


def _wait_canvas_width(page: Any, width: int) -> None:
    page.wait_for_function(f"() => {CANVAS} && {CANVAS}.width === {width}", timeout=30_000)


def _shows_the_game(live: Live, page: Any) -> float:
    shot = decode_data_url(page.evaluate(f"() => {CANVAS}.toDataURL('image/png')"))
    assert float(np.std(shot)) >= 15.0, "blank or flat canvas"
    # Drawn at the display size, the way a page shows a small rung.
    drawn = np.asarray(Image.fromarray(shot).resize((640, 360), Image.Resampling.BILINEAR))
    return max(psnr(thumbnail(drawn), thumb) for _, thumb in live.tap.items())


def test_moq_watch_plays_each_rung_and_switches(live: Live, browser: Any) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 600}, device_scale_factor=1)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        page.goto(f"http://localhost:{live.port}/watch.html?name=game")
        page.wait_for_function(f"() => {ELEMENT}", timeout=30_000)
        seen = {}
        for width, height in ((160, 90), (320, 180), (640, 360), (160, 90)):
            _size_element(page, width, height)
            _wait_canvas_width(page, width)
            page.wait_for_timeout(500)
            seen[(width, height)] = _shows_the_game(live, page)
    finally:
        page.close()
    live.stack.check()
    assert errors == []
    print(f"moq-watch on each rendition: best PSNR against the server's frames {seen}")
    assert all(db >= MIN_MATCH_DB for db in seen.values()), seen
