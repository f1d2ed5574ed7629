"""Game sound, Opus encoding, the audio capture clock and the audio track (no browser)."""

from __future__ import annotations

import itertools
import json
import threading
from dataclasses import dataclass
from pathlib import Path

import av
import numpy as np
import numpy.typing as npt
import pytest

from server.frames.frame import Camera, FrameFlags, FrameMeta
from server.frames.timing import Stage
from server.game.sounds import SCENE_TONES_HZ, GameSounds, ToneSource
from server.media.audio_encode import (
    FRAME_SAMPLES,
    SAMPLE_RATE,
    AudioPacket,
    OpusEncoder,
    encode_varint,
    legacy_frame,
)
from server.media.catalog import Catalog, VideoSection, audio_section
from server.moq.wire import Reader
from server.session.audio_capture import HOLD_BACK_NS, AudioCapture, AudioStamps, CapturedAudio
from server.session.broadcast import AUDIO_GROUP_FRAMES, TRACKS
from server.session.timing_track import decode_timing
from tests.test_encode_catalog import HANG_MISSING, HANG_REASON, run_with_hang
from tests.test_session_broadcast import Harness

FRAME_US = FRAME_SAMPLES * 1_000_000 // SAMPLE_RATE


def dominant_hz(samples: npt.NDArray[np.float32], rate: int = SAMPLE_RATE) -> float:
    window = np.hanning(samples.size)
    spectrum = np.abs(np.fft.rfft(samples * window))
    return float(np.argmax(spectrum) * rate / samples.size)


def decode_opus(packets: list[AudioPacket]) -> npt.NDArray[np.float32]:
    decoder = av.CodecContext.create("libopus", "r")
    decoder.sample_rate = SAMPLE_RATE  # type: ignore[attr-defined]
    decoder.layout = "mono"  # type: ignore[attr-defined]
    out: list[npt.NDArray[np.float32]] = []
    for p in packets:
        for frame in decoder.decode(av.Packet(p.payload)):  # type: ignore[attr-defined]
            out.append(frame.to_ndarray().astype(np.float32).reshape(-1))
    return np.concatenate(out)


def test_opus_round_trip_keeps_the_tone_and_one_packet_per_frame() -> None:
    encoder = OpusEncoder()
    tone = ToneSource(440.0)
    packets: list[AudioPacket] = []
    for i in range(50):
        got = encoder.encode(tone.render(FRAME_SAMPLES), i * FRAME_SAMPLES)
        assert len(got) == 1  # no lookahead queue: each frame's packet comes out at once
        packets += got
    assert [p.duration_us for p in packets] == [FRAME_US] * 50
    # Stamped with each input frame's time: exactly one frame apart.
    steps = {b.pts_us - a.pts_us for a, b in itertools.pairwise(packets)}
    assert steps == {FRAME_US}
    decoded = decode_opus(packets)
    assert abs(dominant_hz(decoded[4800:]) - 440.0) < 5.0


def test_legacy_frame_is_varint_pts_then_the_packet() -> None:
    packet = AudioPacket(pts_us=1_234_567, duration_us=20_000, payload=b"\x01\x02opus")
    frame = legacy_frame(packet)
    reader = Reader(frame, complete=True)
    assert reader.varint() == 1_234_567
    assert frame.endswith(b"\x01\x02opus")
    for value in (0, 63, 64, 16383, 16384, 2**30 - 1, 2**30, 2**62 - 1):
        assert Reader(encode_varint(value), complete=True).varint() == value
    with pytest.raises(ValueError):
        encode_varint(2**62)


def test_catalog_audio_section_has_what_moq_watch_reads() -> None:
    catalog = Catalog(
        video=VideoSection(renditions={}),
        audio=audio_section(sample_rate=48_000, channels=1, bitrate=64_000, frame_ms=20),
    )
    doc = json.loads(catalog.to_json())
    assert doc["audio"] == {
        "renditions": {
            "audio": {
                "codec": "opus",
                "container": {"kind": "legacy"},
                "sampleRate": 48_000,
                "numberOfChannels": 1,
                "bitrate": 64_000,
                "jitter": 20,
            }
        }
    }


def moving_meta(frame_id: int, dx: float, flags: FrameFlags = FrameFlags.NONE) -> FrameMeta:
    cam = Camera.identity()
    view = cam.view.copy()
    view[0, 3] = -dx * frame_id
    prev = cam.view.copy()
    prev[0, 3] = -dx * (frame_id - 1)
    moved = Camera(view, cam.proj, prev, cam.prev_proj, cam.near, cam.far, cam.fov_y_deg)
    return FrameMeta(frame_id, moved, flags=flags)


def test_game_sounds_follow_the_camera_the_scene_and_controls() -> None:
    sounds = GameSounds()
    sounds.frame(moving_meta(0, 0.0))  # the first frame seen starts the first scene
    assert sounds.scene == 0
    still = sounds.render(4800)
    assert abs(dominant_hz(still) - SCENE_TONES_HZ[0]) < 8
    assert float(np.abs(still).max()) < 0.1  # the tone alone is soft
    for i in range(1, 32, 2):  # 3.1 m at 0.1 m a frame, every other frame seen: five steps
        sounds.frame(moving_meta(i, 0.1))
    assert sounds.steps == 5
    assert float(np.abs(sounds.render(4800)).max()) > 0.2  # a footstep is loud
    sounds.frame(moving_meta(40, 50.0))  # a teleport is no walk: a cut whose RESET we missed
    assert sounds.steps == 5 and sounds.scene == 1
    sounds.frame(moving_meta(41, 50.0, FrameFlags.RESET))  # a cut: the next tone
    assert sounds.scene == 2
    sounds.render(4800)
    assert abs(dominant_hz(sounds.render(9600)) - SCENE_TONES_HZ[2]) < 8
    quiet = float(np.abs(sounds.render(960)).max())
    sounds.click()
    assert float(np.abs(sounds.render(960)).max()) > quiet + 0.1


@dataclass
class FakeClock:
    mono: int = 10_000_000_000

    def monotonic_ns(self) -> int:
        return self.mono

    def wall_ns(self) -> int:
        return self.mono + 1_700_000_000_000_000_000


def capture_with(
    source: ToneSource | GameSounds,
) -> tuple[AudioCapture, list[CapturedAudio], FakeClock]:
    from server.session.audio_capture import _Clock

    fake = FakeClock()
    out: list[CapturedAudio] = []
    capture = AudioCapture(
        source,
        OpusEncoder(),
        out.append,
        origin_ns=fake.mono,
        clock=_Clock(monotonic_ns=fake.monotonic_ns, wall_ns=fake.wall_ns),
    )
    return capture, out, fake


def test_minutes_of_silence_do_not_drift_from_the_clock() -> None:
    """Ten simulated minutes of a silent source, stepped at uneven intervals."""
    source = ToneSource(440.0)
    source.silent = True
    capture, out, clock = capture_with(source)
    rng = np.random.default_rng(1)
    for _ in range(30_000):
        clock.mono += int(rng.uniform(5e6, 35e6))
        capture.step()
    elapsed_us = (clock.mono - capture.origin_ns - HOLD_BACK_NS) // 1000
    pts = [c.packet.pts_us for c in out]
    assert all(b - a == FRAME_US for a, b in itertools.pairwise(pts))
    # The last packet ends within one frame of the clock: no drift after 10 minutes.
    assert abs(pts[-1] + FRAME_US - elapsed_us) <= FRAME_US
    assert elapsed_us > 9 * 60 * 1_000_000
    # Opus makes silence tiny: a few bytes per packet.
    assert max(len(c.packet.payload) for c in out[10:]) < 16
    assert capture.stats.gaps == 0 and not capture.stats.failed


def test_a_source_that_stops_and_starts_keeps_the_clock() -> None:
    capture, out, clock = capture_with(ToneSource(440.0))
    for _ in range(50):
        clock.mono += 20_000_000
        capture.step()
    before = len(out)
    capture.paused = True
    for _ in range(100):  # two seconds stopped
        clock.mono += 20_000_000
        capture.step()
    paused_packets = len(out) - before
    assert paused_packets <= 1  # at most the partial frame, padded, goes out
    capture.paused = False
    for _ in range(50):
        clock.mono += 20_000_000
        capture.step()
    jumps = [
        (a.packet.pts_us, b.packet.pts_us)
        for a, b in itertools.pairwise(out)
        if b.packet.pts_us - a.packet.pts_us != FRAME_US
    ]
    assert len(jumps) == 1
    gap = jumps[0][1] - jumps[0][0]
    assert abs(gap - 2_000_000 - FRAME_US) <= 2 * FRAME_US  # the pause, on the clock
    flagged = [c for c in out if c.discontinuity]
    assert len(flagged) == 1 and flagged[0].packet.pts_us == jumps[0][1]
    assert capture.stats.gaps == 1


def test_frame_events_sound_at_their_time_or_at_once_when_late() -> None:
    sounds = GameSounds()
    capture, _out, clock = capture_with(sounds)
    clock.mono += 400_000_000
    capture.step()
    made_until = capture._next
    # A frame rendered after the last step: its time is still to be made.
    meta = moving_meta(1, 0.0, FrameFlags.RESET)
    meta.stamps[Stage.RENDER_START, 0] = clock.mono + 10_000_000
    clock.mono += 40_000_000
    capture.frame(meta)
    capture.step()
    assert sounds.scene == 0 and capture.stats.late_events == 0
    assert made_until is not None and capture._next is not None
    assert capture._next == (clock.mono - HOLD_BACK_NS - capture.origin_ns) * SAMPLE_RATE // 10**9
    # A frame rendered 100 ms ago: too late for its sample, it sounds at once.
    late = moving_meta(2, 0.0, FrameFlags.RESET)
    late.stamps[Stage.RENDER_START, 0] = clock.mono - 100_000_000
    capture.frame(late)
    capture.step()
    assert sounds.scene == 1 and capture.stats.late_events == 1
    assert abs(capture.stats.event_lag_ns[-1] - (100_000_000 - HOLD_BACK_NS)) < 1_000_000


def test_a_failing_encoder_turns_audio_off_and_nothing_else() -> None:
    class Broken(OpusEncoder):
        def encode(self, samples: npt.NDArray[np.float32], pts_samples: int) -> list[AudioPacket]:
            raise RuntimeError("codec gone")

    out: list[CapturedAudio] = []
    capture = AudioCapture(ToneSource(440.0), Broken(), out.append, origin_ns=0)
    capture.start()
    deadline = threading.Event()
    for _ in range(100):
        if capture.stats.failed:
            break
        deadline.wait(0.05)
    assert capture.stats.failed and not out
    capture.stop()
    assert not capture._thread.is_alive()


def test_audio_track_groups_and_timing_records() -> None:
    h = Harness(audio=True)  # a broadcast with sound
    assert h.broadcast.tracks == TRACKS
    audio = h.pipe.server.subscribe("game", "audio")
    timing = h.pipe.server.subscribe("game", "timing")
    h.sync()
    h.publish(0, keyframe=True)  # opens the timing group
    stamps = AudioStamps(sample=1, capture=2, encode_start=3, encode_end=4)
    for i in range(AUDIO_GROUP_FRAMES + 7):
        packet = AudioPacket(pts_us=i * FRAME_US, duration_us=FRAME_US, payload=bytes([i]))
        jump = i == AUDIO_GROUP_FRAMES + 2
        h.broadcast.publish_audio(CapturedAudio(packet, stamps, discontinuity=jump))
    h.sync()
    frames = h.frames(audio)
    # Groups of AUDIO_GROUP_FRAMES, and a new group where the pts jumped.
    assert [seq for seq, _ in frames] == [0] * AUDIO_GROUP_FRAMES + [1, 1] + [2] * 5
    pts = [Reader(p, complete=True).varint() for _, p in frames]
    assert pts == [i * FRAME_US for i in range(AUDIO_GROUP_FRAMES + 7)]
    records = [decode_timing(p) for _, p in h.frames(timing)]
    audio_records = [r for r in records if r.get("kind") == "audio"]
    assert len(audio_records) == AUDIO_GROUP_FRAMES + 7 and "pts_us" not in audio_records[0]
    assert set(audio_records[0]["stamps"]) == {
        "audio_sample",
        "audio_capture",
        "audio_encode_start",
        "audio_encode_end",
        "audio_publish",
    }


_HANG_AUDIO_JS = """
import { readFileSync } from "node:fs";
import * as Catalog from "HANG/catalog/index.js";
import * as Legacy from "HANG/container/legacy.js";
const parsed = Catalog.RootSchema.parse(JSON.parse(readFileSync(process.argv[2], "utf8")));
const frames = new Legacy.Format().decode(new Uint8Array(readFileSync(process.argv[3])));
console.log(JSON.stringify({ audio: parsed.audio,
  frames: frames.map((f) => [f.timestamp, f.payload.length]) }));
"""


@pytest.mark.skipif(HANG_MISSING, reason=HANG_REASON)
def test_hang_reads_our_audio_catalog_and_frames(tmp_path: Path) -> None:
    """@moq/hang's own schema and legacy container (what @moq/watch uses) on our bytes."""
    from server.media.catalog import catalog_for
    from server.media.encode import EncoderConfig, VideoEncoder

    section = audio_section(sample_rate=48_000, channels=1, bitrate=64_000, frame_ms=10)
    catalog = catalog_for(VideoEncoder(EncoderConfig(320, 180, fps=30)), audio=section)
    (tmp_path / "catalog.json").write_bytes(catalog.to_json())
    packet = OpusEncoder().encode(ToneSource(440.0).render(FRAME_SAMPLES), 48_000 * 5)[0]
    (tmp_path / "frame.bin").write_bytes(legacy_frame(packet))
    out = run_with_hang(tmp_path, _HANG_AUDIO_JS, tmp_path / "catalog.json", tmp_path / "frame.bin")
    rendition = out["audio"]["renditions"]["audio"]
    assert rendition["codec"] == "opus" and rendition["container"] == {"kind": "legacy"}
    assert (rendition["sampleRate"], rendition["numberOfChannels"]) == (48_000, 1)
    assert out["frames"] == [[5_000_000, len(packet.payload)]]


@pytest.mark.parametrize("audio", [True, False])
def test_audio_flag_sets_the_catalog_and_the_tracks(audio: bool) -> None:
    from typing import cast

    from server.frames.frame import Size
    from server.frames.ring import FrameRing
    from server.session.runner import StreamingSession, StreamSettings

    settings = StreamSettings(relay_url="http://localhost:1/", fps=30, audio=audio)
    # The ring is only read once the session runs; this test never runs it.
    session = StreamingSession(settings, cast(FrameRing, None), Size(320, 180))
    catalog = json.loads(session.broadcast.catalog_json)
    assert ("audio" in catalog) is audio
    assert ("audio" in session.broadcast.tracks) is audio
    assert (session.audio_encoder is not None) is audio
