"""Sound end to end: a known tone from the session reaches the audio output of our
player and of the unmodified @moq/watch element.

The session plays a pure 880 Hz tone (ToneSource) instead of the game's mix; the
page's AudioContext starts on a click (the gesture browsers require) and an
AnalyserNode on the player's output finds the tone's frequency. The same run
reads the page's audio latency (capture -> heard) and A/V offset windows. @moq/watch
has no hooks: an init script puts an analyser beside whatever node it connects to
the AudioContext's destination.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from server.bench.latency import LiveStack
from server.game.sounds import GameSounds, ToneSource
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


@pytest.fixture(scope="module")
def stack() -> Iterator[LiveStack]:
    config = SessionConfig(scene="default", render_size=RENDER, display_size=DISPLAY, fps=FPS)
    with LiveStack(config, audio=True, sound=ToneSource(TONE_HZ)) as live:
        yield live


def _is_tone(reads: list[list[float]], hz: float = TONE_HZ) -> list[float]:
    """The levels (dB) of the reads whose loudest bin is the tone's."""
    return [db for f, db in reads if abs(f - hz) < 2 * 48000 / 8192]


def test_player_plays_the_tone_and_measures_sync(stack: LiveStack, browser: Any) -> None:
    page = open_player(browser, stack.player_url(overlay="0"), frames=5)
    assert not stats(page)["audio"]["running"]  # no gesture yet: the browser holds it
    page.click("#audio-mute")  # the first gesture starts the sound
    page.wait_for_function(
        "() => window.upcast.stats().audio.running && window.upcast.stats().audio.decoded > 20",
        timeout=20_000,
    )
    # The first seconds are the sync target settling (its arrival window is 3 s, so a
    # slow start stays in it that long; each move is a faded jump); what must be
    # continuous is what follows.
    page.wait_for_timeout(3000)
    found = page.evaluate(ANALYSE)
    print("audio reads:", json.dumps(found))
    assert found["state"] == "running"
    tone = _is_tone(found["reads"])
    # A real tone (not the noise floor) in at least 7 of 8 reads.
    assert sum(db > -40 for db in tone) >= 7, (found, stats(page)["audio"])
    before = stats(page)["framesPresented"]
    audio = stack.session.audio if stack.session else None
    assert audio is not None
    cpu0, t0 = audio.stats.encode_ns, time.monotonic()
    settled = len(stats(page)["latency"]["av_offset"]["samples"])
    time.sleep(8)  # let the latency and offset windows fill
    cpu_share = (audio.stats.encode_ns - cpu0) / 1e9 / (time.monotonic() - t0)
    summary = _summary(page)
    # The offsets of these 8 s (the window also holds the first second's settling).
    offsets = np.abs(np.array(stats(page)["latency"]["av_offset"]["samples"][settled:]))
    summary["abs_av_offset"] = {
        "p50": float(np.percentile(offsets, 50)),
        "p95": float(np.percentile(offsets, 95)),
    }
    summary["audio_cpu_share_of_a_core"] = cpu_share
    print("audio e2e:", json.dumps(summary))
    assert summary["framesPresented"] > before + 20  # video went on (2 loaded cores)
    lat = summary["latency"]
    assert lat["audio_total"]["n"] > 50 and lat["av_offset"]["n"] > 20
    summary["abs_av_offset"]["p90"] = float(np.percentile(offsets, 90))
    # The target: sound and picture within +-40 ms, for 9 frames in 10. (A freshly
    # started stack used to leave the sound 60-95 ms behind for seconds: one stall of
    # the page, such as a first read of these stats, moved the sound's 95th-percentile
    # arrival; ArrivalBound now counts a stall once.)
    assert summary["abs_av_offset"]["p90"] <= 40, summary["abs_av_offset"]
    # Mute: the output goes quiet, video does not care.
    page.click("#audio-mute")
    time.sleep(0.3)
    muted = page.evaluate(ANALYSE)
    assert max(db for _, db in muted["reads"]) < min(tone) - 30, (muted, found)
    page.close()
    stack.check()


# Block the page's main thread (where video and sound are decoded) for ``ms``.
STALL = "(ms) => { const t = performance.now(); while (performance.now() - t < ms) {} }"


def test_a_stall_of_the_page_does_not_pull_sound_and_picture_apart(
    stack: LiveStack, browser: Any
) -> None:
    """One 80 ms stall of the page (where video and sound are decoded): sound and
    picture stay together over the next three seconds; only the frames shown late right
    after the stall may be off. (With a 1 s arrival window and pictures held at most
    60 ms, a stall moved the sound about 70 ms later for a second, which the picture
    could not follow: offsets of -69 to -85 ms.)"""
    page = open_player(browser, stack.player_url(overlay="0"), frames=5)
    page.click("#status")  # any gesture starts the sound (not the mute button: see the join test)
    page.wait_for_function(
        "() => window.upcast.stats().audio.running && window.upcast.stats().audio.decoded > 20",
        timeout=20_000,
    )
    page.wait_for_timeout(4000)  # settle: the 3 s arrival window past the start
    assert not stats(page)["audio"]["muted"]
    target_before = stats(page)["audio"]["sync"]["targetMs"]
    start = len(stats(page)["latency"]["av_offset"]["samples"])
    page.evaluate(STALL, 80)
    page.wait_for_timeout(3000)
    after = stats(page)
    signed = np.array(after["latency"]["av_offset"]["samples"][start:])
    offsets = np.abs(signed)
    target_after = after["audio"]["sync"]["targetMs"]
    print(
        f"stall: target {target_before:.1f} -> {target_after:.1f} ms, "
        f"|A/V| p50 {np.percentile(offsets, 50):.1f} p90 {np.percentile(offsets, 90):.1f} "
        f"max {offsets.max():.1f} ms over {offsets.size} frames"
    )
    # A loaded machine shows 15-30 fps; what matters is the offsets of the frames shown.
    assert offsets.size >= 20, offsets.size
    assert np.percentile(offsets, 90) <= 40, (
        np.round(signed, 1).tolist(),
        after["audio"]["sync"],
        {k: after["audio"][k] for k in ("videoHeld", "videoHeldMeanMs", "underrunFrames")},
    )
    page.close()


# The sound's sync target and what the worklet holds, every 100 ms for 3 s from now:
# what a failure of the join test reports (rows of TRACE_FIELDS).
TRACE_FIELDS = (
    "ms", "targetMs", "arrivalMs", "videoMs", "aheadMs", "bufferedMs", "underrunFrames",
    "concealedFrames", "decoded", "framesPresented", "videoHeld",
)  # fmt: skip
TRACE_SYNC = """() => {
    const t0 = performance.now();
    const round = (x) => (x === undefined ? null : Math.round(x));
    window.__syncTrace = [];
    const timer = setInterval(() => {
        const s = window.upcast.stats();
        const a = s.audio;
        const y = a.sync || {};
        window.__syncTrace.push([
            round(performance.now() - t0), round(y.targetMs), round(y.arrivalMs),
            round(y.videoMs), round(y.aheadMs), round(a.bufferedMs), a.underrunFrames,
            a.concealedFrames, a.decoded, s.framesPresented, a.videoHeld,
        ]);
        if (performance.now() - t0 > 3000) clearInterval(timer);
    }, 100);
}"""

# Milliseconds from now until the player's output carries the tone (polled every 20 ms).
UNTIL_TONE = """async (hz) => {
    const out = window.upcast.audioOutput();
    const analyser = out.context.createAnalyser();
    analyser.fftSize = 2048;
    analyser.smoothingTimeConstant = 0;
    out.connect(analyser);
    const t0 = performance.now();
    const bins = new Float32Array(analyser.frequencyBinCount);
    const bin = Math.round(hz * analyser.fftSize / out.context.sampleRate);
    while (performance.now() - t0 < 10000) {
        analyser.getFloatFrequencyData(bins);
        if (bins[bin] > -40) break;
        await new Promise((r) => setTimeout(r, 20));
    }
    out.disconnect(analyser);
    return performance.now() - t0;
}"""


def test_a_player_joining_mid_stream_plays_at_once(stack: LiveStack, browser: Any) -> None:
    """The stream has been running for a while: a new page starts at the relay's latest
    audio group, its sound starts within a second of the gesture and then stays."""
    page = open_player(browser, stack.player_url(overlay="0"), frames=3)
    # Any gesture starts the sound (the mute button would mute a page the browser already
    # lets play: Chromium lets an origin that had a gesture autoplay in its next page).
    page.click("#status")
    page.evaluate(TRACE_SYNC)
    to_sound_ms = page.evaluate(UNTIL_TONE, TONE_HZ)
    found = page.evaluate(ANALYSE)
    trace = page.evaluate("() => window.__syncTrace")
    print(f"joined mid-stream: tone heard {to_sound_ms:.0f} ms after the gesture; {found}")
    assert to_sound_ms < 1000
    assert sum(db > -40 for db in _is_tone(found["reads"])) >= 7, (found, TRACE_FIELDS, trace)
    page.close()


# Put an analyser beside every node a page connects to its AudioContext's destination.
TAP_DESTINATION = """(() => {
  const connect = AudioNode.prototype.connect;
  window.__taps = [];
  AudioNode.prototype.connect = function (dest, ...rest) {
    const out = connect.call(this, dest, ...rest);
    if (dest instanceof AudioDestinationNode) {
      const ctx = this.context;
      if (!ctx.__tap) {
        ctx.__tap = ctx.createAnalyser();
        ctx.__tap.fftSize = 8192;
        ctx.__tap.smoothingTimeConstant = 0;
        window.__taps.push(ctx.__tap);
      }
      connect.call(this, ctx.__tap);
    }
    return out;
  };
})();"""

READ_TAPS = """async () => {
    const reads = [];
    for (let k = 0; k < 8; k++) {
        await new Promise((r) => setTimeout(r, 200));
        for (const a of window.__taps) {
            const bins = new Float32Array(a.frequencyBinCount);
            a.getFloatFrequencyData(bins);
            let best = 0;
            for (let i = 1; i < bins.length; i++) if (bins[i] > bins[best]) best = i;
            reads.push([best * a.context.sampleRate / a.fftSize, bins[best]]);
        }
    }
    return reads;
}"""


def test_moq_watch_element_plays_the_tone(stack: LiveStack, browser: Any) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 600})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.add_init_script(TAP_DESTINATION)
    try:
        page.goto(f"http://localhost:{stack.port}/watch.html?name=game&muted=0")
        canvas = "document.querySelector('moq-watch canvas')"
        page.wait_for_function(f"() => {canvas} && {canvas}.width === 640", timeout=30_000)
        page.mouse.click(400, 300)  # the gesture its AudioContext waits for
        page.wait_for_function("() => window.__taps.length > 0", timeout=10_000)
        page.wait_for_timeout(1500)
        reads = page.evaluate(READ_TAPS)
    finally:
        page.close()
    print("moq-watch audio reads:", reads)
    assert errors == []
    assert sum(db > -40 for db in _is_tone(reads)) >= 7, reads


def test_the_game_sounds_follow_its_frames() -> None:
    """The reference game's own mix on a live stack: the orbiting camera walks, the first
    frame sets the scene's tone, and frame events sound within the pipeline's lag."""
    config = SessionConfig(scene="dolly", render_size=RENDER, display_size=DISPLAY, fps=FPS)
    with LiveStack(config, audio=True) as live:
        time.sleep(6)
        session = live.session
        assert session is not None and session.audio is not None
        sounds, stats_ = session.sound, session.audio.stats
        assert isinstance(sounds, GameSounds)
        lag_ms = np.array(stats_.event_lag_ns) / 1e6
        print(
            f"game sound: {sounds.steps} steps, scene {sounds.scene}, {stats_.packets} packets, "
            f"event lag p50 {np.percentile(lag_ms, 50):.1f} ms p95 {np.percentile(lag_ms, 95):.1f}"
        )
        assert sounds.scene == 0  # the first frame seen set the first scene's tone
        assert sounds.steps >= 5  # the dolly moves the camera: footsteps
        assert stats_.packets >= 6 / 0.01 * 0.8 and stats_.gaps == 0 and not stats_.failed
        assert float(np.percentile(lag_ms, 50)) < 150
        live.check()
