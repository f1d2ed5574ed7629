"""The player's AudioWorklet under loss, a stopped source, a moved offset and minutes
of silence, rendered in Chromium's OfflineAudioContext (faster than real time).

The worklet source is taken from client_web/src/audio_worklet.ts, the very text the
bundle embeds. A 440 Hz sine is cut into 20 ms chunks on a media clock and fed to the
worklet as the page would, a little ahead of their play time; the rendered output is
compared, sample by sample, with the sine at the media position it should be playing:
exact where the stream has data (so no drift, however long), silent once a gap has
lasted longer than its concealment (a repeated period for 10 ms, faded out over the
next 50; tests/test_audio_concealment.py checks what it plays), and never a step larger
than the sine itself makes (no clicks at any edge, concealment's included).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from tests.browser.conftest import DIST
from tests.chromium import browser_marks

pytestmark = browser_marks(DIST / "index.html")

SOURCE = (Path(__file__).resolve().parents[2] / "client_web/src/audio_worklet.ts").read_text()
NAME = re.search(r'WORKLET_NAME = "([^"]+)"', SOURCE)
BODY = re.search(r"WORKLET_SOURCE = `(.*)`;", SOURCE, re.DOTALL)
# The sine's own largest step: 2 pi f A / rate.
SINE_STEP = 2 * 3.141592653589793 * 440 * 0.5 / 48_000

RENDER = """async ({ source, name, seconds, drops, offsetMoves }) => {
    const rate = 48000, chunk = 960, lead = 4800;
    const length = rate * seconds;
    const ctx = new OfflineAudioContext({ numberOfChannels: 1, length, sampleRate: rate });
    const blob = new Blob([source], { type: "text/javascript" });
    await ctx.audioWorklet.addModule(URL.createObjectURL(blob));
    const node = new AudioWorkletNode(ctx, name, { outputChannelCount: [1] });
    node.connect(ctx.destination);
    const dropped = new Set(drops);
    const sine = (m) => 0.5 * Math.sin((2 * Math.PI * 440 * m) / rate);
    let offset = lead;
    node.port.postMessage({ type: "offset", offset });
    let next = 0; // next chunk to send
    const feed = (untilFrame) => {
        while ((next + 1) * chunk + offset <= untilFrame) {
            if (!dropped.has(next)) {
                const data = new Float32Array(chunk);
                for (let i = 0; i < chunk; i++) data[i] = sine(next * chunk + i);
                node.port.postMessage({ type: "chunk", start: next * chunk, data });
            }
            next++;
        }
    };
    // Feed each half second 0.5 s ahead of its play time, as a page would.
    const step = rate / 2;
    const moves = new Map(offsetMoves);
    for (let at = step; at < rate * seconds; at += step) {
        ctx.suspend(at / rate).then(() => {
            if (moves.has(at)) {
                offset += moves.get(at);
                node.port.postMessage({ type: "offset", offset });
            }
            feed(at + step * 2);
            // Port messages reach the audio thread asynchronously and offline rendering
            // is far faster than real time: give them a moment before going on.
            setTimeout(() => ctx.resume(), 30);
        });
    }
    feed(step * 2);
    await new Promise((r) => setTimeout(r, 200)); // the processor's port is live
    const out = (await ctx.startRendering()).getChannelData(0);
    // Which media frame each output frame should play, for the checks below.
    const offsets = []; // [from frame, offset]
    let o = lead;
    offsets.push([0, o]);
    for (const [at, d] of offsetMoves) { o += d; offsets.push([at, o]); }
    let maxStep = 0, maxErr = 0, checked = 0, gapRms = 0, gapN = 0, k = 0;
    for (let j = 1; j < out.length; j++) maxStep = Math.max(maxStep, Math.abs(out[j] - out[j - 1]));
    for (let j = 0; j < out.length; j++) {
        while (k + 1 < offsets.length && offsets[k + 1][0] <= j) k++;
        const m = j - offsets[k][1];
        if (m < 0) continue;
        const c = Math.floor(m / chunk);
        // After a move the worklet fades out, jumps, and (moved later) waits for media it
        // already played and dropped: skip 40 ms after one.
        if (j - offsets[k][0] < 2 * chunk && k > 0) continue;
        if (dropped.has(c)) {
            // 60 ms or more into a gap (chunks of 20 ms): concealment has faded out.
            const deep = dropped.has(c - 1) && dropped.has(c - 2) && dropped.has(c - 3);
            if (deep && dropped.has(c + 1)) { gapRms += out[j] * out[j]; gapN++; }
        } else if (!dropped.has(c - 1) && c >= 1) {
            maxErr = Math.max(maxErr, Math.abs(out[j] - sine(m)));
            checked++;
        }
    }
    return { maxStep, maxErr, checked, gapRms: gapN ? Math.sqrt(gapRms / gapN) : 0, gapN };
}"""


@pytest.fixture
def render(web_root: str, browser: Any) -> Any:
    assert NAME is not None and BODY is not None, "audio_worklet.ts changed shape"
    source = BODY.group(1).replace("${WORKLET_NAME}", NAME.group(1))
    page = browser.new_page()
    page.goto(f"{web_root}/style.css")  # any page on localhost: a secure context

    def run(seconds: float, drops: list[int], offset_moves: list[list[int]] | None = None) -> Any:
        args = {
            "source": source,
            "name": NAME.group(1),
            "seconds": seconds,
            "drops": drops,
            "offsetMoves": offset_moves or [],
        }
        return page.evaluate(RENDER, args)

    yield run
    page.close()


def test_exact_and_click_free_with_no_loss(render: Any) -> None:
    got = render(3, [])
    assert got["checked"] > 100_000
    assert got["maxErr"] < 1e-5, got
    assert got["maxStep"] < SINE_STEP * 1.05, got


def test_ten_percent_packet_loss_makes_no_clicks_and_no_drift(render: Any) -> None:
    import random

    rng = random.Random(7)
    drops = [c for c in range(300) if rng.random() < 0.1]
    got = render(6, drops)
    print("10 % loss:", got)
    assert got["checked"] > 150_000
    assert got["maxErr"] < 1e-5, got  # every sample that arrived plays at its place
    assert got["maxStep"] < SINE_STEP * 1.05, got  # fades, not cuts


def test_a_source_that_stops_for_a_second_and_starts_again(render: Any) -> None:
    drops = list(range(100, 150))  # 1 s without packets
    got = render(5, drops)
    # Silence once concealment has faded out, not a held buzz or a loop.
    assert got["gapN"] > 40_000 and got["gapRms"] < 1e-3, got
    assert got["maxErr"] < 1e-5, got  # and back in place after it
    assert got["maxStep"] < SINE_STEP * 1.05, got


def test_a_new_offset_is_faded_in_not_cut(render: Any) -> None:
    # The page moves the offset (a new sync target) by 20 ms, then by -15 ms.
    got = render(4, [], [[48_000, 960], [120_000, -720]])
    assert got["maxErr"] < 1e-5, got  # playing the right media frame after each move
    assert got["maxStep"] < SINE_STEP * 1.05, got


def test_two_minutes_then_exact(render: Any) -> None:
    """Two minutes of stream, a few chunks lost here and there: still sample-exact."""
    drops = list(range(500, 6000, 997))
    got = render(120, drops)
    assert got["checked"] > 5_000_000
    assert got["maxErr"] < 1e-5, got
    assert got["maxStep"] < SINE_STEP * 1.05, got
