"""Sound with packets missing (issue 24's hard case): no click storm, no drift.

The session drops Opus packets before it publishes them: 5 % at random and a burst
of 5 (50 ms) every second, what a viewer behind a lossy link gets once the relay has
skipped what could not arrive. Measured against the same page before the loss:
- the tone stays the loudest thing in every spectrum;
- the broadband energy around it (what clicks are made of) stays low: the player
  conceals each gap by repeating the last pitch period (client_web/src/audio_worklet.ts;
  checked sample by sample in tests/test_audio_concealment.py) instead of silence;
- the sound does not drift: capture-to-heard latency after a few seconds of loss is
  where it was, as playback is tied to the output clock plus one offset.
And packets the decoder cannot take (invalid Opus, a frame without a packet) do not end
the sound: WebCodecs closes a decoder after an error, and the page makes a new one.

The spectra count only where the page's playback offset held still. The player moves
that offset when its target moves by 10 ms or more, as a faded jump (2.7 ms out, 2.7 ms
in: client_web/src/audio.ts), which reads as a click in the one spectrum it falls in
(11-15 dB, up to 2 FFT bins off the tone). With the CPU busy, such jumps come without
any loss: one of 110-205 ms about 9 s after the start in most runs (the start-up's
arrivals leaving the page's 3 s window), and on a machine with two busy loops beside
the test 6-10 of about 10 ms in 16 s. Two full-suite runs of this test failed with that
signature in the lossy half (one spectrum 2 bins off, two under 20 dB), as if
concealment had clicked, and the big jump, between the two latency readings, moved
one by 33 ms. So a spectrum read across a jump is left out (and counted); at least half
must remain, and no jump over 20 ms should fall between 3 s before the first latency
reading and the second, else the measurement is repeated once (on a machine with two
busy loops beside the test, jumps of 90-210 ms came in both). Drift is what the latency
moved beyond the offset's own move between the two readings' windows: in a CI run two
11 ms retargets during the loss moved the latency 20.9 ms, which is the design (the
target follows the arrivals), not drift.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import random
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from server.bench.latency import LiveStack
from server.game.sounds import ToneSource
from server.session.audio_capture import CapturedAudio
from server.stack.local import SessionConfig
from tests.e2e.conftest import DISPLAY, FPS, RENDER, needs, open_player, stats

pytestmark = [*needs("index.html"), pytest.mark.timeout(300)]  # up to three measurements

TONE_HZ = 880.0

READS = 16
SAMPLE_RATE = 48_000  # the page's AudioContext (the offset is in its frames)
# A jump of the playback offset beyond the drift check's tolerance: a latency reading
# across one measures the jump, not drift.
MAX_JUMP_MS = 20.0
MEASUREMENTS = 3  # at most, each about 17 s
# Spectra 200 ms apart: the loudest bin's frequency, the tone's power against
# everything more than 20 bins (117 Hz) away from it, in dB, and the page's playback
# offset (frames) right after: a change of it is a jump of the sound (see above).
SPECTRA = """async ([hz, count]) => {
    const offsetNow = () => {
        const sync = window.upcast.stats().audio.sync;
        return sync ? sync.offsetFrames : null;
    };
    const start = offsetNow();
    const out = window.upcast.audioOutput();
    const analyser = out.context.createAnalyser();
    analyser.fftSize = 8192;
    analyser.smoothingTimeConstant = 0;
    out.connect(analyser);
    const bin = Math.round(hz * analyser.fftSize / out.context.sampleRate);
    const reads = [];
    for (let k = 0; k < count; k++) {
        await new Promise((r) => setTimeout(r, 200));
        const db = new Float32Array(analyser.frequencyBinCount);
        analyser.getFloatFrequencyData(db);
        let best = 0, tone = 0, rest = 0;
        for (let i = 1; i < db.length; i++) {
            if (db[i] > db[best]) best = i;
            const p = Math.pow(10, db[i] / 10);
            if (Math.abs(i - bin) <= 4) tone += p;
            else if (Math.abs(i - bin) > 20) rest += p;
        }
        const hz = best * out.context.sampleRate / analyser.fftSize;
        reads.push([hz, 10 * Math.log10(tone / rest), offsetNow()]);
    }
    out.disconnect(analyser);
    return {start, reads};
}"""


class Lossy:
    """Wraps the session's audio publish: drops packets while ``on``; the next packets
    get the Opus data queued in ``replace`` instead of theirs."""

    def __init__(self, publish: Any, seed: int = 7) -> None:
        self._publish = publish
        self._random = random.Random(seed)
        self.on = False
        self.sent = 0
        self.dropped = 0
        self.replace: list[bytes] = []

    def __call__(self, captured: CapturedAudio) -> None:
        if self.replace:
            bad = dataclasses.replace(captured.packet, payload=self.replace.pop(0))
            captured = dataclasses.replace(captured, packet=bad)
        if self.on:
            burst = self.sent % 100 < 5  # 5 packets of every 100 (50 ms a second)
            if burst or self._random.random() < 0.05:
                self.dropped += 1
                self.sent += 1
                return
        self.sent += 1
        self._publish(captured)


@pytest.fixture(scope="module")
def lossy_stack() -> Iterator[tuple[LiveStack, Lossy]]:
    config = SessionConfig(scene="default", render_size=RENDER, display_size=DISPLAY, fps=FPS)
    with LiveStack(config, audio=True, sound=ToneSource(TONE_HZ)) as live:
        session = live.session
        assert session is not None
        lossy = Lossy(session.broadcast.publish_audio)
        session.broadcast.publish_audio = lossy  # type: ignore[method-assign]
        yield live, lossy


def _latency_p50(page: Any) -> float:
    return float(stats(page)["latency"]["audio_total"]["p50"])


@dataclasses.dataclass
class Spectrum:
    hz: float  # the loudest bin's frequency
    db: float  # the tone's power against the broadband rest
    steady: bool  # the playback offset did not move while it was read


def _spectra(page: Any, offsets: list[int | None]) -> list[Spectrum]:
    """READS spectra; the playback offset at each is appended to ``offsets``."""
    found = page.evaluate(SPECTRA, [TONE_HZ, READS])
    read_offsets = [found["start"]] + [read[2] for read in found["reads"]]
    offsets += read_offsets
    return [
        Spectrum(hz=read[0], db=read[1], steady=read_offsets[k] == read_offsets[k + 1])
        for k, read in enumerate(found["reads"])
    ]


def _offset(page: Any) -> int | None:
    sync = stats(page)["audio"].get("sync") or {}
    return sync.get("offsetFrames")


def _wait_watching_offset(page: Any, seconds: float, offsets: list[int | None]) -> None:
    """Wait, reading the playback offset every 200 ms into ``offsets``."""
    for _ in range(round(seconds / 0.2)):
        page.wait_for_timeout(200)
        offsets.append(_offset(page))


@dataclasses.dataclass
class LossMeasurement:
    clean: list[Spectrum]
    lossy: list[Spectrum]
    latency_before: float
    latency_after: float
    underrun_clean: int
    underrun_lossy: int
    concealed_lossy: int
    dropped_lossy: int
    # The playback offset from 6 s before the first latency reading to the second.
    offsets: list[int | None]
    # How many of those readings came before the first latency reading, and how many
    # in the 6 s before the second (each reading's window of packets).
    before_count: int
    after_count: int

    def _jumps_ms(self) -> list[float]:
        known = [o for o in self.offsets if o is not None]
        return [abs(b - a) / SAMPLE_RATE * 1000 for a, b in itertools.pairwise(known)]

    @property
    def largest_jump_ms(self) -> float:
        return max(self._jumps_ms(), default=0.0)

    @property
    def moved_ms(self) -> float:
        """How far the offset moved between the two latency readings' windows (the
        medians of its readings in each): what it moved the latency by, by design."""
        before = [o for o in self.offsets[: self.before_count] if o is not None]
        after = [o for o in self.offsets[-self.after_count :] if o is not None]
        if not before or not after:
            return 0.0
        return float(np.median(after) - np.median(before)) / SAMPLE_RATE * 1000

    @property
    def steady_lossy(self) -> list[Spectrum]:
        return [s for s in self.lossy if s.steady]


def _measure(page: Any, lossy: Lossy) -> LossMeasurement:
    """Spectra and latency clean, then after 6 s of loss, with the loss on meanwhile."""
    offsets: list[int | None] = []
    # The latency window holds 6 s of packets: its first reading must not span a jump.
    _wait_watching_offset(page, 3.0, offsets)
    underrun_start = stats(page)["audio"]["underrunFrames"]
    clean = _spectra(page, offsets)
    latency_before = _latency_p50(page)
    before_count = len(offsets)
    underrun_clean = stats(page)["audio"]["underrunFrames"] - underrun_start
    lossy.on = True
    try:
        _wait_watching_offset(page, 6.0, offsets)  # any drift would accumulate
        loss_start = len(offsets) - 15  # the last 3 s of it
        underrun_start = stats(page)["audio"]["underrunFrames"]
        concealed_start = stats(page)["audio"]["concealedFrames"]
        dropped_start = lossy.dropped
        lossy_spectra = _spectra(page, offsets)
        latency_after = _latency_p50(page)
        audio = stats(page)["audio"]
    finally:
        lossy.on = False
    return LossMeasurement(
        clean=clean,
        lossy=lossy_spectra,
        latency_before=latency_before,
        latency_after=latency_after,
        underrun_clean=underrun_clean,
        underrun_lossy=audio["underrunFrames"] - underrun_start,
        concealed_lossy=audio["concealedFrames"] - concealed_start,
        dropped_lossy=lossy.dropped - dropped_start,
        offsets=offsets,
        before_count=before_count,
        after_count=len(offsets) - loss_start,
    )


def test_lost_packets_make_no_click_storm_and_no_drift(
    lossy_stack: tuple[LiveStack, Lossy], browser: Any
) -> None:
    live, lossy = lossy_stack
    page = open_player(browser, live.player_url(overlay="0"), frames=5)
    try:
        page.click("#audio-mute")
        page.wait_for_function(
            "() => window.upcast.stats().audio.running && window.upcast.stats().audio.decoded > 50",
            timeout=20_000,
        )
        page.wait_for_timeout(3500)  # the start-up's latencies leave the 6 s window
        # Up to three measurements: the first without a jump over MAX_JUMP_MS, else the
        # one whose largest jump was smallest (in a CI run both of two had 38-85 ms jumps
        # and the offset moved 400 ms between the readings: nothing left to judge drift by).
        tries: list[LossMeasurement] = []
        for attempt in range(MEASUREMENTS):
            m = _measure(page, lossy)
            tries.append(m)
            if len(m.steady_lossy) >= READS // 2 and m.largest_jump_ms <= MAX_JUMP_MS:
                break
            if attempt < MEASUREMENTS - 1:
                print(
                    f"audio loss: {READS - len(m.steady_lossy)} spectra across a jump, the"
                    f" largest {m.largest_jump_ms:.0f} ms: measuring again"
                )
        m = min(tries, key=lambda t: (len(t.steady_lossy) < READS // 2, t.largest_jump_ms))
    finally:
        page.close()
    steady = m.steady_lossy
    ratio_clean = float(np.median([s.db for s in m.clean if s.steady] or [s.db for s in m.clean]))
    ratio_lossy = float(np.median([s.db for s in steady]))
    summary = {
        "dropped": lossy.dropped,
        "sent": lossy.sent,
        "tone_to_rest_db": {"clean": ratio_clean, "lossy": ratio_lossy},
        "capture_to_heard_p50_ms": {"before": m.latency_before, "after": m.latency_after},
        # While the spectra were read: output frames without their sample, of them
        # those concealed, and the frames the packets dropped meanwhile held (480 each).
        "underrun_frames": {"clean": m.underrun_clean, "lossy": m.underrun_lossy},
        "concealed_frames_lossy": m.concealed_lossy,
        "dropped_frames_lossy": m.dropped_lossy * 480,
        "largest_jump_ms": m.largest_jump_ms,
        "offset_moved_ms": m.moved_ms,
        "spectra_across_a_jump": {
            "clean": sum(not s.steady for s in m.clean),
            "lossy": sum(not s.steady for s in m.lossy),
        },
    }
    lossy_reads = [(round(s.hz, 1), round(s.db, 1), s.steady) for s in m.lossy]
    print("audio loss:", json.dumps(summary), json.dumps(lossy_reads))
    assert len(steady) >= READS // 2, ("the sound jumped in most spectra, twice", summary)
    assert lossy.dropped > 50
    # The tone is still the loudest in every spectrum read without a jump.
    assert all(abs(s.hz - TONE_HZ) < 12 for s in steady), lossy_reads
    # The gaps were concealed (a burst longer than the concealment's 60 ms and gaps
    # right after one end in silence, hence not all of them).
    assert m.concealed_lossy > 0.7 * m.dropped_lossy * 480, summary
    # The tone stays well above the broadband rest, in nearly every spectrum. Gaps
    # played as silence (faded over 2.7 ms, the player before concealment): medians
    # 14.7-45.6 dB in 6 runs (1 in CI), single spectra with a gap near their middle
    # 11-17 in every run. Concealed: medians 39.2 and 42.5 in 2 runs (16 spectra), the
    # worst single spectrum 29.3; tests/test_audio_concealment.py measures the same
    # difference without a browser (32.1 -> 46.3 dB median, worst 10.3 -> 28.4).
    ratios = [s.db for s in steady]
    assert ratio_lossy > 28.0, summary
    assert sum(r > 20.0 for r in ratios) >= len(ratios) - 1, (summary, ratios)
    # No drift: the same latency, within a jitter buffer's worth, beyond what the page's
    # own moves of its playback offset account for.
    drift = m.latency_after - m.latency_before - m.moved_ms
    if m.largest_jump_ms <= MAX_JUMP_MS:
        assert abs(drift) < 20.0, summary
    else:
        # All three measurements spanned jumps of the offset (a starved page retargets
        # its buffer to the arrivals: in a CI run 38-85 ms jumps moved it 400 ms between
        # the readings while the latency moved 14 ms): the medians no longer say how much
        # of the offset's move the latency should show. What is left to check is the
        # harm drift does: the latency must not have grown beyond the offset's moves.
        # A jump inside a reading's 6 s window puts that reading's median anywhere between
        # the levels on either side of it, which the offsets' medians do not follow: a CI
        # run with a 31 ms jump saw the latency grow 29.9 ms against an offset move of
        # 9.1 ms. So one largest jump more is allowed; the failure this guards against
        # (gaps played in addition to the sound, not in its place) adds the lost time,
        # about 100 ms for every second of this loss, 600 ms by the second reading.
        allowed = 20.0 + max(0.0, m.moved_ms) + m.largest_jump_ms
        print(f"audio loss: jumps in every measurement; latency growth {drift:.1f} ms checked")
        assert m.latency_after - m.latency_before < allowed, summary
    live.check()


def test_an_undecodable_packet_does_not_end_the_sound(
    lossy_stack: tuple[LiveStack, Lossy], browser: Any
) -> None:
    """WebCodecs closes a decoder after an error: the page makes a new one and the sound
    goes on (before, one bad packet silenced the page until it reloaded)."""
    live, lossy = lossy_stack
    page = open_player(browser, live.player_url(overlay="0"), frames=5)
    try:
        page.click("#audio-mute")
        page.wait_for_function("() => window.upcast.stats().audio.decoded > 50", timeout=20_000)
        before = after = stats(page)["audio"]
        # On a loaded machine the relay may skip the audio group the bad packets rode in
        # (the page then never sees them: a CI run got 1 of 2 empty frames and no invalid
        # packet): inject again, at most three times, until the page has met them.
        injections = 0
        while injections < 3 and not (
            after["decoderErrors"] >= 1 and after["malformed"] > before["malformed"]
        ):
            injections += 1
            # Three invalid packets (TOC code 3, a count of 63 frames of 20 ms: longer than
            # Opus' 120 ms), then two frames with a timestamp and no packet at all.
            lossy.replace = [b"\xff\xff\xff\xff"] * 3 + [b""] * 2
            page.wait_for_function(
                f"() => window.upcast.stats().audio.decoded > {after['decoded']} + 150",
                timeout=10_000,
            )
            after = stats(page)["audio"]
    finally:
        page.close()
    counts = ("decoded", "decoderErrors", "decoderRestarts", "malformed")
    print("bad packets:", injections, "injections:", {k: after[k] for k in counts})
    assert after["decoderErrors"] >= 1, after  # the bad packets did break the decoder
    assert after["decoderRestarts"] >= 1, after
    # The sound went on: 150 packets decoded after the last injection (waited above).
    # Each empty frame is counted and dropped, never decoded: at most two an injection.
    assert 1 <= after["malformed"] - before["malformed"] <= 2 * injections, after
    live.check()
