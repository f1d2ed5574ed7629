"""A captured application's own sound reaches the player (issues 22 and 24).

The "application" plays a 660 Hz tone through ``pacat`` into the PulseAudio server
its session started (server/game/x11/pulse.py); the session records the sink's
monitor (server/session/pulse_monitor.py) and streams it; an AnalyserNode on the
player's output finds the tone. An xmessage window gives the stream a picture.
"""

from __future__ import annotations

import json
import shlex
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.bench.latency import LiveStack
from server.stack.local import SessionConfig
from tests.e2e.conftest import needs, open_player, stats
from tests.e2e.test_audio_e2e import ANALYSE

pytestmark = needs("index.html")

TONE_HZ = 660.0
TONE_APP = Path(__file__).resolve().parent.parent / "x11_tone_app.py"


@pytest.fixture(scope="module")
def stack() -> Iterator[LiveStack]:
    for program in ("pulseaudio", "pacat", "parec", "xmessage"):
        if shutil.which(program) is None:
            pytest.fail(
                f"{program} is missing: .ci/run installs pulseaudio pulseaudio-utils x11-utils"
            )
    tone = shlex.join([sys.executable, str(TONE_APP), str(TONE_HZ)])
    play = "pacat --playback --rate=48000 --channels=1 --format=float32le --latency-msec=20"
    app = shlex.join(["sh", "-c", f"xmessage -geometry 320x180+0+0 sound & {tone} | {play}"])
    config = SessionConfig(
        source="x11", app=app, render_size="320x180", display_size="640x360", fps=30
    )
    with LiveStack(config, audio=True) as live:
        yield live


def test_the_applications_tone_is_heard_in_the_player(stack: LiveStack, browser: Any) -> None:
    page = open_player(browser, stack.player_url(overlay="0"), frames=5, timeout_s=60)
    try:
        page.click("#audio-mute")  # the gesture that starts the sound
        page.wait_for_function(
            "() => window.upcast.stats().audio.running && window.upcast.stats().audio.decoded > 20",
            timeout=20_000,
        )
        page.wait_for_timeout(1500)
        found = page.evaluate(ANALYSE)
        total = stats(page)["latency"]["audio_total"]
        print(
            "x11 sound:",
            json.dumps(found),
            "capture -> heard p50",
            total["p50"],
            "p95",
            total["p95"],
        )
        tone = [db for hz, db in found["reads"] if abs(hz - TONE_HZ) < 2 * 48000 / 8192]
        assert sum(db > -40 for db in tone) >= 7, found
        stack.check()
    finally:
        page.close()
