"""Sound end to end: a known tone from the session reaches the player's audio output.

The session plays a pure 880 Hz tone (ToneSource) instead of the game's mix; the
page's AudioContext starts on a click (the gesture browsers require) and an
AnalyserNode on the player's output finds the tone's frequency. The same run
reads the page's audio latency (capture -> heard) and A/V offset windows.
"""

from __future__ import annotations

import json
import time
from typing import Any

import pytest

from server.bench.latency import LiveStack
from server.game.sounds import ToneSource
from server.stack.local import SessionConfig
from tests.e2e.conftest import DISPLAY, FPS, RENDER, needs, open_player, stats

pytestmark = [*needs("index.html"), pytest.mark.timeout(180)]

TONE_HZ = 880.0

# Eight unsmoothed spectra 200 ms apart: the tone must be there in (nearly) all of
# them, so a player that drops out often fails, not only one that is silent.
ANALYSE = """async () => {
    const out = window.upcast.audioOutput();
    const analyser = out.context.createAnalyser();
    analyser.fftSize = 8192;
    analyser.smoothingTimeConstant = 0;
    out.connect(analyser);
    const reads = [];
    for (let k = 0; k < 8; k++) {
        await new Promise((r) => setTimeout(r, 200));
        const bins = new Float32Array(analyser.frequencyBinCount);
        analyser.getFloatFrequencyData(bins);
        let best = 0;
        for (let i = 1; i < bins.length; i++) if (bins[i] > bins[best]) best = i;
        reads.push([best * out.context.sampleRate / analyser.fftSize, bins[best]]);
    }
    out.disconnect(analyser);
    return { reads, state: out.context.state };
}"""


def _summary(page: Any) -> dict[str, Any]:
    s = stats(page)
    lat = s["latency"]
    keys = ("audio_capture", "audio_encode", "audio_publish", "audio_network",
            "audio_decode", "audio_play", "audio_total", "av_offset", "total")  # fmt: skip
    return {
        "audio": s["audio"],
        "framesPresented": s["framesPresented"],
        "latency": {
            k: {"p50": lat[k]["p50"], "p95": lat[k]["p95"], "n": lat[k]["n"]} for k in keys
        },
    }


def test_player_plays_the_tone_and_measures_sync(browser: Any) -> None:
    config = SessionConfig(scene="default", render_size=RENDER, display_size=DISPLAY, fps=FPS)
    with LiveStack(config, audio=True, sound=ToneSource(TONE_HZ)) as stack:
        page = open_player(browser, stack.player_url(overlay="0"), frames=5)
        assert not stats(page)["audio"]["running"]  # no gesture yet: the browser holds it
        page.click("#audio-mute")  # the first gesture starts the sound
        page.wait_for_function(
            "() => window.upcast.stats().audio.running && window.upcast.stats().audio.decoded > 20",
            timeout=20_000,
        )
        found = page.evaluate(ANALYSE)
        print("audio reads:", json.dumps(found))
        assert found["state"] == "running"
        tone = [db for hz, db in found["reads"] if abs(hz - TONE_HZ) < 2 * 48000 / 8192]
        # A real tone (not the noise floor) in at least 7 of 8 reads.
        assert sum(db > -40 for db in tone) >= 7, found
        before = stats(page)["framesPresented"]
        time.sleep(8)  # let the latency and offset windows fill
        summary = _summary(page)
        print("audio e2e:", json.dumps(summary))
        assert summary["framesPresented"] > before + 20  # video went on (2 loaded cores)
        lat = summary["latency"]
        assert lat["audio_total"]["n"] > 50 and lat["av_offset"]["n"] > 20
        # The target is +-40 ms; measured here: audio 65-155 ms behind the picture
        # (see the report). This bound only catches a sync that is lost altogether.
        assert abs(lat["av_offset"]["p50"]) <= 250, lat["av_offset"]
        # Mute: the output goes quiet, video does not care.
        page.click("#audio-mute")
        time.sleep(0.3)
        muted = page.evaluate(ANALYSE)
        assert max(db for _, db in muted["reads"]) < min(tone) - 30, (muted, found)
        stack.check()
