"""Spectators on the rendition ladder (issue 44), the real stack end to end.

The stack of tests/e2e/test_stream_e2e.py (display 640x360, 30 fps) with the ladder
on (divisors 2 and 4: rungs ``video.320x180`` and ``video.160x90`` after the player's
``video``). What is checked, in headless Chromium:
- a page without a token chooses among the rungs with its ABR (client_web/src/abr.ts)
  and plays one, showing the frames the server encoded under the ids it reports (the
  rungs' frames carry the player's track's pts, so the timing track applies); a page
  with the player's token plays the player's track, as before the ladder;
- ``?rendition=<track>`` plays that track and never switches; ``?abr=off`` plays the
  first (the player's track);
- told to (``window.upcast.rendition``), a spectator moves to another rung without a
  lost frame, without showing a frame older than one it showed (the relay replays the
  new rung's latest group from its keyframe, up to a second back), and back; then
  ``rendition(null)`` hands the choice back to its ABR;
- on a link narrowed to 250 kbit/s (the network emulator, server/net) a spectator on
  the 188 kbit/s rung moves down to the 100 kbit/s one by itself and stays there. (The
  timing track takes 130-170 kbit/s of the link at 20-30 fps, as fast as this machine
  runs the stack: the upper rung and it need 280-340 kbit/s, the lower one and it
  200-250.)
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator
from typing import Any
from urllib.parse import urlencode

import pytest

from server.bench.latency import LiveStack
from server.net.emulator import EmulatorThread
from server.net.link_profile import LinkProfile, Schedule
from server.serve.snapshots import snapshot_psnr
from server.stack.local import SessionConfig
from tests.e2e.conftest import DISPLAY, FPS, RENDER, FrameTap, Live, needs, open_player, stats

pytestmark = [*needs("index.html"), pytest.mark.timeout(180)]

HIGH, LOW = "video.320x180", "video.160x90"
SIZES = {HIGH: (320, 180), LOW: (160, 90), "video": (640, 360)}
MIN_PSNR_DB = 20.0  # tests/e2e/test_stream_e2e.py MIN_PSNR_EACH_DB
CABLE = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=15.0)
NARROW = LinkProfile.both_ways(rate_bps=280e3, rtt_ms=40.0)


@pytest.fixture(scope="module")
def ladder() -> Iterator[Live]:
    tap = FrameTap()
    config = SessionConfig(scene="default", render_size=RENDER, display_size=DISPLAY, fps=FPS)
    with LiveStack(config, frame_tap=tap, ladder=(2, 4)) as stack:
        yield Live(stack, tap)
        stack.check()


def spectator_url(live: Live, **query: str) -> str:
    """The player page without a token: a spectator."""
    params = {"broadcast": live.stack.broadcast, "overlay": "0", **query}
    return f"http://localhost:{live.port}/?" + urlencode(params)


def _plays(page: Any, seconds: float = 2.0) -> dict[str, Any]:
    """Stats after ``seconds`` more of play; frames must have kept coming."""
    before = stats(page)["framesPresented"]
    page.wait_for_timeout(seconds * 1000)
    after = stats(page)
    assert after["framesPresented"] > before + seconds * 5, (before, after["framesPresented"])
    return after


def _size(s: dict[str, Any]) -> tuple[int, int]:
    return s["width"], s["height"]


def test_a_spectator_plays_a_rung_and_the_player_its_own_track(ladder: Live, browser: Any) -> None:
    page = open_player(browser, spectator_url(ladder))
    try:
        s = _plays(page)
        assert page.evaluate("() => window.upcast.viewOnly") is True
        assert s["abr"]["mode"] == "abr"
        assert s["abr"]["ladder"] == [LOW, HIGH]  # the rungs, cheapest first
        # The start: the highest rung under 500 kbit/s (both are): the 188 kbit/s one.
        assert s["rendition"] == HIGH, s["abr"]
        assert _size(s) == SIZES[HIGH]
        assert s["errors"] == [] and s["framesLost"] == 0
        assert s["recovery"]["keyframeRequests"] == 0  # it cannot ask
        same = snapshot_psnr(page, ladder.tap, count=4)
        print(f"spectator on {s['rendition']}: PSNR against the server's frame {same}")
        assert min(same) >= MIN_PSNR_DB, same
    finally:
        page.close()
    player = open_player(browser, ladder.player_url())
    try:
        s = _plays(player)
        assert (s["rendition"], s["abr"]["mode"], _size(s)) == ("video", "player", SIZES["video"])
        assert s["renditionSwitches"] == 0 and s["errors"] == []
    finally:
        player.close()
    ladder.stack.check()


@pytest.mark.parametrize(
    ("query", "track", "mode"),
    [({"rendition": LOW}, LOW, "forced"), ({"abr": "off"}, "video", "first")],
)
def test_the_url_chooses_the_rendition(
    ladder: Live, browser: Any, query: dict[str, str], track: str, mode: str
) -> None:
    page = open_player(browser, spectator_url(ladder, **query))
    try:
        s = _plays(page, 3.0)
        assert (s["rendition"], s["abr"]["mode"], _size(s)) == (track, mode, SIZES[track])
        assert s["renditionSwitches"] == 0
        assert s["renditionSeconds"].keys() == {track}
        assert s["errors"] == []
        if track != "video":
            # A rung has a group every second; the player's track, at the player's rate, may
            # be skipped a group on this loaded machine (the relay's latency bound).
            assert s["framesLost"] == 0
    finally:
        page.close()


def test_a_spectator_switches_when_told_without_going_back_in_time(
    ladder: Live, browser: Any
) -> None:
    # Forced from the start: the ABR may move a page of this loaded machine by itself.
    page = open_player(browser, spectator_url(ladder, rendition=HIGH), frames=10)
    try:
        first = stats(page)
        assert first["rendition"] == HIGH
        # What the canvas shows, read every 30 ms in the page across both switches.
        page.evaluate(
            """() => { window.shown = []; window.shownTimer = setInterval(() => {
                const pts = window.upcast.stats().lastPresentedPtsUs;
                if (pts !== undefined) window.shown.push(pts);
            }, 30); }"""
        )
        t0 = time.monotonic()
        assert page.evaluate(f"() => window.upcast.rendition({json.dumps(LOW)})") is True
        page.wait_for_function(
            f"() => window.upcast.stats().rendition === {json.dumps(LOW)}", timeout=5000
        )
        down_s = time.monotonic() - t0
        low = _plays(page)
        assert _size(low) == SIZES[LOW] and low["abr"]["mode"] == "forced"
        assert page.evaluate(f"() => window.upcast.rendition({json.dumps(HIGH)})") is True
        page.wait_for_function(
            f"() => window.upcast.stats().rendition === {json.dumps(HIGH)}", timeout=5000
        )
        back = _plays(page)
        shown = page.evaluate("() => { clearInterval(window.shownTimer); return window.shown; }")
        assert page.evaluate("() => window.upcast.rendition(null)") is True  # the ABR again
        auto = _plays(page, 1.0)
    finally:
        page.close()
    summary = {
        "switch_s": round(down_s, 2),
        "took_ms": [low["abr"]["lastSwitch"]["tookMs"], back["abr"]["lastSwitch"]["tookMs"]],
        "switches": back["renditionSwitches"],
        "seconds": back["renditionSeconds"],
        "hidden": back["abr"]["hiddenFrames"],
        "longest_freeze_ms": back["longestFreezeMs"],
        "lost": back["framesLost"],
        "skipped": back["groupsSkipped"],
    }
    print("switches:", json.dumps(summary))
    assert back["renditionSwitches"] == 2, summary
    assert back["abr"]["lastSwitch"]["from"] == LOW and back["abr"]["lastSwitch"]["to"] == HIGH
    assert set(back["renditionSeconds"]) == {HIGH, LOW}
    # The new rung's numbering continues the old one's: nothing counted lost, unless the
    # relay skipped a group (this loaded machine can make it).
    assert back["framesLost"] == 0 or back["groupsSkipped"] > 0, summary
    assert back["errors"] == [] and _size(back) == SIZES[HIGH]
    # Never an older frame than one already shown (the replayed group is decoded, not shown).
    assert len(shown) > 50
    assert all(b >= a for a, b in itertools.pairwise(shown)), shown
    assert auto["abr"]["mode"] == "abr" and auto["rendition"] in (HIGH, LOW), auto["abr"]
    assert down_s < 3.0, summary


def test_a_spectator_on_a_narrow_link_moves_down_by_itself(ladder: Live, browser: Any) -> None:
    lead_s = 3.0
    schedule = Schedule.of([(0.0, CABLE), (lead_s, NARROW)])
    with EmulatorThread(
        upstream=("127.0.0.1", ladder.port), schedule=schedule, tcp_passthrough=True
    ) as net:
        page = open_player(browser, spectator_url(ladder, port=str(net.port)), frames=10)
        try:
            net.restart_schedule()
            t_narrow = time.monotonic() + lead_s
            page.wait_for_timeout(lead_s * 1000 - 300)
            before = stats(page)
            page.wait_for_function(
                f"() => window.upcast.stats().rendition === {json.dumps(LOW)}", timeout=15_000
            )
            down_s = time.monotonic() - t_narrow
            at_low = stats(page)
            after = _plays(page, 6.0)
        finally:
            page.close()
        link = net.stats()["down"]
    summary = {
        "down_after_s": round(down_s, 2),
        "reason": at_low["abr"]["lastSwitch"],
        "switches": after["renditionSwitches"],
        "seconds": after["renditionSeconds"],
        "skipped": after["groupsSkipped"] - before["groupsSkipped"],
        "estimate_bps": after["abr"]["estimateBps"],
        "fps": after["fps"],
        "link_bytes": link.get("bytes_delivered"),
    }
    print("narrow link:", json.dumps(summary))
    assert before["rendition"] == HIGH and before["renditionSwitches"] == 0, summary
    # Down by itself, and no probe back up over a link that cannot carry the upper rung.
    assert after["rendition"] == LOW and after["renditionSwitches"] == 1, summary
    assert down_s < 10.0, summary
    assert after["errors"] == [] and after["status"].startswith("subscribed"), summary
