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


def _summary(s: dict[str, Any]) -> dict[str, Any]:
    """The page's audio stats and latency percentiles from one ``stats`` snapshot."""
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


# How many windows a test may measure, and how much output starvation (ms within a
# window, see _starved_frames) still counts as a fed page.
MEASUREMENTS = 3
STARVED_MS = 100.0
SAMPLE_RATE = 48_000  # the page's AudioContext runs at Opus's rate


def _measure_sync(page: Any, audio: Any) -> tuple[dict[str, Any], bool]:
    """Eight seconds of the live page: its latency summary, the |A/V offset| percentiles of
    the frames shown in the window, and whether its audio output was fed throughout."""
    start = stats(page)
    before, starved0 = start["framesPresented"], _starved_frames(start)
    settled = len(start["latency"]["av_offset"]["samples"])
    cpu0, t0 = audio.stats.encode_ns, time.monotonic()
    time.sleep(8)  # let the latency and offset windows fill
    cpu_share = (audio.stats.encode_ns - cpu0) / 1e9 / (time.monotonic() - t0)
    end = stats(page)  # one snapshot: the summary, the offsets and the starvation agree
    summary = _summary(end)
    offsets = np.abs(np.array(end["latency"]["av_offset"]["samples"][settled:]))
    summary["abs_av_offset"] = {
        f"p{q}": float(np.percentile(offsets, q)) if offsets.size else float("inf")
        for q in (50, 90, 95)
    }
    starved_ms = (_starved_frames(end) - starved0) / SAMPLE_RATE * 1000
    summary.update(framesBefore=before, starvedMs=starved_ms, audio_cpu_share_of_a_core=cpu_share)
    return summary, starved_ms < STARVED_MS


def _starved_frames(page_stats: dict[str, Any], concealed: bool = False) -> int:
    """Output frames the page's worklet played silent while chunks were due (underrun),
    plus, with ``concealed``, those it filled in by concealment. (Concealment is routine
    on a loaded machine, 120-470 ms in 8 s of windows whose sync was fine, so it marks a
    starved window only where a dropout is what is measured.)"""
    audio = page_stats["audio"]
    return int(audio["underrunFrames"]) + (int(audio["concealedFrames"]) if concealed else 0)


def _analyse_fed(page: Any) -> dict[str, Any]:
    """ANALYSE's reads, taken again (up to MEASUREMENTS times) while the page's output
    starved during them: a dropout of a starved output is the machine's load, not the
    player's. The reads themselves are held to the same bar however many are taken."""
    for _ in range(MEASUREMENTS):
        starved0 = _starved_frames(stats(page), concealed=True)
        found: dict[str, Any] = page.evaluate(ANALYSE)
        starved = _starved_frames(stats(page), concealed=True) - starved0
        starved_ms = starved / SAMPLE_RATE * 1000
        found["starvedMs"] = starved_ms
        if starved_ms < STARVED_MS:
            break
    return found


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
    found = _analyse_fed(page)
    print("audio reads:", json.dumps(found))
    assert found["state"] == "running"
    tone = _is_tone(found["reads"])
    # A real tone (not the noise floor) in at least 7 of 8 reads.
    assert sum(db > -40 for db in tone) >= 7, (found, stats(page)["audio"])
    audio = stack.session.audio if stack.session else None
    assert audio is not None
    # Up to MEASUREMENTS windows of 8 s: the first one in which the page was fed (its
    # output starved for under STARVED_MS) is held to the sync target. On a loaded 2-core
    # machine the page itself can miss its audio deadlines for a whole window (a CI run:
    # 13975 frames of underrun, offsets p90 146 ms with p50 13 ms); a starved output plays
    # late whatever the player does, so such a window is measured again.
    for attempt in range(1, MEASUREMENTS + 1):
        summary, fed = _measure_sync(page, audio)
        print(f"audio e2e (window {attempt}):", json.dumps(summary))
        assert summary["framesPresented"] > summary["framesBefore"] + 20  # video went on
        lat = summary["latency"]
        assert lat["audio_total"]["n"] > 50 and lat["av_offset"]["n"] > 20
        if fed:
            break
    # The target: sound and picture within +-40 ms, for 9 frames in 10, in a fed window.
    # (A freshly started stack used to leave the sound 60-95 ms behind for seconds: one
    # stall of the page, such as a first read of these stats, moved the sound's
    # 95th-percentile arrival; ArrivalBound now counts a stall once.) When every window
    # starved, the player must still centre the sound on the picture: the median.
    offsets = summary["abs_av_offset"]
    if fed:
        assert offsets["p90"] <= 40, offsets
    else:
        assert offsets["p50"] <= 40, offsets
    # Mute: the output goes quiet, video does not care.
    page.click("#audio-mute")
    time.sleep(0.3)
    muted = page.evaluate(ANALYSE)
    assert max(db for _, db in muted["reads"]) < min(tone) - 30, (muted, found)
    page.close()
    stack.check()


# Block the page's main thread (where video and sound are decoded) for ``ms``.
STALL_MS = 80
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
    # Up to MEASUREMENTS stalls, 3 s apart: the first whose window the page's output
    # was otherwise fed through (underrun under STARVED_MS beyond the stall's own) is
    # held to the bar; on a machine loaded beyond the stall every window starves, and
    # the median must still hold.
    for attempt in range(1, MEASUREMENTS + 1):
        before = stats(page)
        target_before = before["audio"]["sync"]["targetMs"]
        start = len(before["latency"]["av_offset"]["samples"])
        page.evaluate(STALL, STALL_MS)
        page.wait_for_timeout(3000)
        after = stats(page)
        signed = np.array(after["latency"]["av_offset"]["samples"][start:])
        offsets = np.abs(signed)
        starved_ms = (_starved_frames(after) - _starved_frames(before)) / SAMPLE_RATE * 1000
        fed = starved_ms < STARVED_MS + STALL_MS
        print(
            f"stall {attempt}: target {target_before:.1f} -> "
            f"{after['audio']['sync']['targetMs']:.1f} ms, |A/V| p50 "
            f"{np.percentile(offsets, 50):.1f} p90 {np.percentile(offsets, 90):.1f} max "
            f"{offsets.max():.1f} ms over {offsets.size} frames, starved {starved_ms:.0f} ms"
        )
        # A loaded machine shows 15-30 fps; what matters is the offsets of the frames shown.
        assert offsets.size >= 20, offsets.size
        if fed:
            break
    bound = np.percentile(offsets, 90) if fed else np.percentile(offsets, 50)
    assert bound <= 40, (
        fed,
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
    found = _analyse_fed(page)
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
        started = time.monotonic()
        time.sleep(6)
        session = live.session
        assert session is not None and session.audio is not None
        sounds, stats_ = session.sound, session.audio.stats
        assert isinstance(sounds, GameSounds)
        # Steps follow the camera's travel in game time, which a loaded machine renders
        # slower than the wall clock (a CI run: 4 steps in 6 s at 17 fps of 30): wait for
        # the frames, not the seconds, up to a limit.
        deadline = started + 20
        while sounds.steps < 5 and time.monotonic() < deadline:
            time.sleep(0.2)
        elapsed = time.monotonic() - started
        lag_ms = np.array(stats_.event_lag_ns) / 1e6
        print(
            f"game sound: {sounds.steps} steps in {elapsed:.1f} s, scene {sounds.scene}, "
            f"{stats_.packets} packets, "
            f"event lag p50 {np.percentile(lag_ms, 50):.1f} ms p95 {np.percentile(lag_ms, 95):.1f}"
        )
        assert sounds.scene == 0  # the first frame seen set the first scene's tone
        assert sounds.steps >= 5  # the dolly moves the camera: footsteps
        # Sound is paced by its own clock (10 ms packets), not by the frames.
        assert stats_.packets >= 6 / 0.01 * 0.8 and stats_.gaps == 0 and not stats_.failed
        assert float(np.percentile(lag_ms, 50)) < 150
        live.check()
