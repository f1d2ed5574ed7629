"""Real, unmodified programs streamed to headless Chromium (issue 22).

SuperTux (2D, SDL's renderer) and Neverball (OpenGL through Mesa's llvmpipe), both
from Debian's packages, run on an Xvfb that the session starts; the page plays the
stream and its keys reach the game through XTest. Render size = display size here,
so a frame the session encoded is the captured frame itself (bilinear at 1x is a
copy): the canvas is compared with it by frame id.

Thresholds: the same frame >= 35 dB (issue 22). Key effects are checked as each
game should react: SuperTux leaves its level intro on Enter and scrolls the level
while the right arrow is held; Neverball's menu (a mouse menu) opens the item clicked.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.bench.app.presets import PRESETS, PresetError
from server.bench.latency import LiveStack
from server.serve.snapshots import snapshot_psnr
from server.stack.local import SessionConfig
from tests.chromium import picture_point
from tests.e2e.conftest import (
    FrameTap,
    Live,
    needs,
    open_player,
    stats,
)

pytestmark = needs("index.html")

SIZE = "640x360"
FPS = 30.0
SAME_FRAME_DB = 35.0
# 1.5 Mbit/s for 640x360 at 30 fps: twice the default's scaling of 6 Mbit/s at 720p60.
# At that default (0.75 Mbit/s) Neverball's menu, with its star field, measured
# 34.2 dB; screen content (text, sprites) wants more bits than the built-in scenes.
BITRATE = 1_500_000


def supertux_command(home: Path) -> str:
    return _command("supertux", home)


def neverball_command(home: Path) -> str:
    return _command("neverball", home)


def _command(preset: str, home: Path) -> str:
    try:
        return PRESETS[preset].command(SIZE, home)
    except PresetError as exc:
        pytest.fail(f"{exc} (.ci/run installs it)")


def start_app(app: str) -> Iterator[Live]:
    tap = FrameTap()
    config = SessionConfig(
        source="x11", app=app, render_size=SIZE, display_size=SIZE, fps=FPS, upscaler="bilinear"
    )
    with LiveStack(config, frame_tap=tap, bitrate=BITRATE) as stack:
        yield Live(stack, tap)
        stack.check()


def newest(tap: FrameTap) -> tuple[int, Any]:
    items = tap.items()
    assert items, "no frame encoded yet"
    return items[-1]


def poll(predicate: Any, timeout_s: float) -> float | None:
    """Poll until ``predicate()``; the seconds it took, or None after ``timeout_s``."""
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 >= timeout_s:
            return None
        time.sleep(0.03)
    return time.monotonic() - t0


def wait_for(predicate: Any, timeout_s: float, what: str) -> float:
    """Poll until ``predicate()``; returns the seconds it took."""
    took = poll(predicate, timeout_s)
    assert took is not None, f"{what}: not within {timeout_s:.0f} s"
    return took


STILL_LEVELS = 0.5  # mean thumbnail change (0-255) below which the picture is still
STILL_S = 2.5  # still this long: x264 has refined the static picture for that long


def wait_until_still(live: Live, timeout_s: float = 12.0) -> float:
    """Wait until the server's picture has not changed for ``STILL_S`` (or ``timeout_s``
    passed; the checks after it then judge); returns the seconds waited. A game keeps
    moving for a while after a key (Tux slides on, the camera follows, something in
    the level animates), and each change costs the encoder about a second of
    climbing quality at the test's bitrate: a fixed wait measured that climb now
    and then."""
    t0 = time.monotonic()
    still_since = t0
    _, last = newest(live.tap)
    while time.monotonic() - still_since < STILL_S and time.monotonic() - t0 < timeout_s:
        time.sleep(0.1)
        _, thumb = newest(live.tap)
        if float(np.abs(np.asarray(thumb, np.float32) - last).mean()) > STILL_LEVELS:
            still_since = time.monotonic()
        last = np.asarray(thumb, np.float32)
    return time.monotonic() - t0


def same_frame_db(live: Live, page: Any, count: int = 6) -> list[float]:
    """Canvas snapshots against the server's frame with the same id."""
    return snapshot_psnr(page, live.tap, count)


# -- SuperTux -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def supertux(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    yield from start_app(supertux_command(tmp_path_factory.mktemp("supertux-home")))


def test_supertux_plays_and_follows_the_keys(supertux: Live, browser: Any) -> None:
    live = supertux
    page = open_player(browser, live.player_url(), frames=10, timeout_s=60)
    try:
        page.wait_for_function("() => window.upcast.stats().inputSubscribers > 0", timeout=10_000)
        # The level's intro: a dark screen with its title, until a key is pressed.
        wait_for(lambda: newest(live.tap)[1].mean() < 40, 30, "SuperTux's intro screen")
        intro_db = same_frame_db(live, page)

        page.click("#screen")

        # One CI run never left the intro after Enter, with inputs reaching the game
        # (its stats counted 4 applied); three runs beside two busy loops here did not
        # repeat it. A game may miss a key as a person's would be missed:
        # pressed while it still loads behind the same dark screen, or pressed and
        # released within one of its frames (SuperTux reads key state once a frame;
        # Playwright's bare press releases within a millisecond). So the key is held as
        # a person holds it, and pressed again, as a person would, if nothing happens.
        def in_level() -> bool:
            return bool(newest(live.tap)[1].mean() > 100)

        presses = 1
        page.keyboard.press("Enter", delay=150)
        reaction_s = poll(in_level, 5)
        if reaction_s is None:
            presses = 2
            page.keyboard.press("Enter", delay=150)
            reaction_s = wait_for(in_level, 10, "the level after Enter, pressed twice")

        # The ice below the floor line is a static tiling: it only moves when the
        # camera scrolls, which it does as Tux walks right.
        def floor(thumb: Any) -> Any:
            return thumb[56:, :, :]

        page.wait_for_timeout(1500)
        _, before = newest(live.tap)
        page.wait_for_timeout(1000)
        _, idle = newest(live.tap)
        idle_change = float(np.abs(floor(idle) - floor(before)).mean())
        page.keyboard.down("ArrowRight")
        try:
            page.wait_for_timeout(2000)
            _, walked = newest(live.tap)
        finally:
            page.keyboard.up("ArrowRight")
        walk_change = float(np.abs(floor(walked) - floor(idle)).mean())
        # The camera follows Tux, and Tux slides on after the key: on a loaded CI machine
        # the picture had moved 4.4 at the release where local runs read 13.1 (the key
        # reached the game later, the camera was still catching up). Up to 3 s more of
        # what the walk goes on to show count; with no key the floor did not move at all.
        wanted = max(8.0, 4 * idle_change)
        catch_up = time.monotonic() + 3.0
        while walk_change <= wanted and time.monotonic() < catch_up:
            page.wait_for_timeout(150)
            _, later = newest(live.tap)
            walk_change = max(walk_change, float(np.abs(floor(later) - floor(idle)).mean()))
        # After the walk the picture keeps changing for a while (Tux slides on, the camera
        # follows) and each change costs the encoder about a second of climbing quality at
        # 1.5 Mbit/s: six snapshots 150 ms apart right after the key read 32.8, 33.2, 34.5,
        # 35.8, 36.1, 35.3 dB (a median under the bar in 1 local run of 2 and in a CI run),
        # 1.5 s after it a median of 34.9 once, 3 s after it 36.8-37.3 in 3 runs, and once
        # 47.8, 30.1, 32.7, 34.3, 35.4, 36.4 (the picture changed again during the
        # snapshots). The check is that the canvas shows the server's frame, so it waits
        # for the picture to stay still, then measures.
        settle_s = wait_until_still(live)
        level_db = same_frame_db(live, page)
        s = stats(page)
        photon = s["inputToPhoton"]
        print(
            f"SuperTux: intro {statistics.median(intro_db):.1f} dB, level "
            f"{statistics.median(level_db):.1f} dB (same frame, median of 6); Enter "
            f"(pressed {presses}x) -> level {reaction_s * 1000:.0f} ms on the server; "
            f"still after {settle_s:.1f} s; floor "
            f"change idle {idle_change:.1f} "
            f"vs right arrow {walk_change:.1f}; input-to-photon p50 {photon['p50']} ms p95 "
            f"{photon['p95']} ms ({len(photon['samples'])} presses); level dB {level_db}"
        )
        assert statistics.median(intro_db) >= SAME_FRAME_DB, intro_db
        assert statistics.median(level_db) >= SAME_FRAME_DB, level_db
        assert idle_change < 2.0, idle_change
        assert walk_change > wanted, (idle_change, walk_change)
        assert photon["samples"], "no input-to-photon sample"
        assert s["errors"] == []
        live.stack.check()
    finally:
        page.close()


# -- Neverball ------------------------------------------------------------------------

# Menu items' centres in the 640x360 picture (Play, Replay, Help, Options, Exit).
MENU_Y = {"play": 143 / 360, "replay": 181 / 360, "help": 219 / 360, "options": 257 / 360}


def highlight_row(thumb: Any) -> float | None:
    """Mean row (thumbnail pixels) of the menu's orange highlight, None if none shows."""
    r, g, b = thumb[..., 0], thumb[..., 1], thumb[..., 2]
    orange = (r > 170) & (g > 90) & (g < 190) & (b < 110)
    top = 29  # below the orange title (y < 116 of 360)
    menu = orange[top:, 55:105]  # the menu column: x 220..420 of 640
    rows = np.nonzero(menu)[0]
    return float(rows.mean()) + top if rows.size >= 10 else None


def blue_share(thumb: Any) -> float:
    """How much of the picture is the plain blue of Neverball's option screens."""
    r, b = thumb[..., 0], thumb[..., 2]
    return float(((b > 120) & (b > r + 60)).mean())


@pytest.fixture(scope="module")
def neverball(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    yield from start_app(neverball_command(tmp_path_factory.mktemp("neverball-home")))


def test_neverball_plays_and_its_menu_follows_the_mouse(neverball: Live, browser: Any) -> None:
    """Neverball's menu is driven by the mouse: a click on an item opens its screen."""
    live = neverball
    page = open_player(browser, live.player_url(), frames=10, timeout_s=60)
    try:
        page.wait_for_function("() => window.upcast.stats().inputSubscribers > 0", timeout=10_000)
        wait_for(lambda: highlight_row(newest(live.tap)[1]) is not None, 30, "Neverball's menu")
        menu_db = same_frame_db(live, page)
        assert blue_share(newest(live.tap)[1]) < 0.05  # the menu: space, not the blue screens
        # A click straight on the item, no move before it (the source presses a tick
        # after the pointer's jump, so the menu knows what is under it).
        page.mouse.click(*picture_point(page, 0.5, MENU_Y["options"]), delay=50)
        opened = wait_for(
            lambda: blue_share(newest(live.tap)[1]) > 0.5, 10, "the Options screen after a click"
        )
        photon = stats(page)["inputToPhoton"]
        print(
            f"Neverball: menu {statistics.median(menu_db):.1f} dB (same frame, median of 6); "
            f"click -> Options in {opened * 1000:.0f} ms "
            f"(on the server); input-to-photon p50 {photon['p50']} ms p95 {photon['p95']} ms"
        )
        assert statistics.median(menu_db) >= SAME_FRAME_DB, menu_db
        live.stack.check()
    finally:
        page.close()
