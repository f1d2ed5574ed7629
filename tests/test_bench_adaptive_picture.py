"""The viewed picture of ``upcast bench adaptive``: the decoded stream, scored at game-time
instants with a missing frame scored as the older one still on screen."""

from __future__ import annotations

import base64
import json

import numpy as np
import numpy.typing as npt

from server.bench.adaptive.picture import (
    DecodeCounts,
    RecordedStream,
    StreamRecorder,
    avcc_of,
    decoded_frames,
    game_time_grid,
    render_to_receive_ms,
    score_stream,
)
from server.media.encode import EncoderConfig, VideoEncoder
from server.moq.events import FrameReceived
from server.session.timing_track import encode_timing

U8 = npt.NDArray[np.uint8]


def _flat(value: int, h: int = 16, w: int = 16) -> U8:
    return np.full((h, w, 3), value, np.uint8)


def test_each_instant_scores_the_last_frame_not_after_it() -> None:
    # Frames at game times 0, 100 and 300 ms (the one at 200 was lost); the ground
    # truth's value is the instant's in tens of ms, a frame's is its own.
    frames = [(t * 1000, _flat(t // 10)) for t in (0, 100, 300)]

    def truth(g: int) -> U8:
        return _flat(g // 10_000)

    grid = [0, 50_000, 100_000, 200_000, 250_000, 300_000, 400_000]
    score = score_stream(iter(frames), grid, truth)
    assert score.at_us == grid
    # The frame on screen at each instant: 0, 0, 100, 100 (200 lost), 100, 300, 300.
    shown = [0, 0, 100, 100, 100, 300, 300]
    assert score.shown_age_ms == [g / 1000 - s for g, s in zip(grid, shown, strict=True)]
    for g, s, p in zip(grid, shown, score.psnr_db, strict=True):
        diff = abs(g // 10_000 - s // 10)
        if diff == 0:
            assert p == 100.0  # identical: the ceiling, not inf
        else:
            assert abs(p - 10 * np.log10(255**2 / diff**2)) < 1e-6
    assert score.mean_psnr(lambda t: t in (0, 100_000, 300_000)) == 100.0


def test_instants_before_the_first_frame_are_not_scored() -> None:
    score = score_stream(iter([(500_000, _flat(1))]), [0, 250_000, 500_000], lambda g: _flat(1))
    assert score.at_us == [500_000]
    assert score_stream(iter([]), [0, 1], lambda g: _flat(1)).psnr_db == []


def test_a_picture_below_the_display_size_is_stretched_to_it() -> None:
    score = score_stream(iter([(0, _flat(80, 8, 8))]), [0], lambda g: _flat(80, 16, 16))
    assert score.psnr_db == [100.0]
    assert abs(score.ssim[0] - 1.0) < 1e-6


def test_the_grid_is_absolute_game_time() -> None:
    assert game_time_grid(1_200_000, 2_600_000, 0.5) == [1_500_000, 2_000_000, 2_500_000]
    assert game_time_grid(1_000_000, 1_000_000, 0.5) == [1_000_000]
    assert game_time_grid(1_100_000, 1_200_000, 0.5) == []
    # Half a frame at 30 fps past each multiple: mid-way through the frame on screen.
    assert game_time_grid(1_000_000, 2_100_000, 0.5, 1 / 60) == [1_016_667, 1_516_667, 2_016_667]


def _stream_of(sizes: list[tuple[int, int]], frames_each: int) -> tuple[RecordedStream, list[U8]]:
    """A stream as recorded: one video track per encoded size, every frame with its
    timing record (game time = 2 x its pts, so the two cannot be confused)."""
    stream = RecordedStream()
    sent: list[U8] = []
    pts = 0
    rng = np.random.default_rng(3)
    for n, (w, h) in enumerate(sizes):
        encoder = VideoEncoder(EncoderConfig(w, h, fps=30.0, bitrate=4_000_000))
        track = f"video{n}"
        stream.inits[track] = encoder.init_segment
        base = rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8)
        for i in range(frames_each):
            picture = np.ascontiguousarray(np.kron(np.roll(base, i, axis=1), np.ones((8, 8, 1))))
            picture = picture.astype(np.uint8)
            pts += 33_333
            encoded = encoder.encode(picture, frame_id=len(sent), pts_us=pts)
            stream.fragments.append((float(pts), track, encoded.fragment))
            stream.received_wall_us.setdefault(track, []).append(10_000_000 + pts + 40_000)
            stream.frames[pts] = (2 * pts, 10_000_000 + pts)
            sent.append(picture)
    return stream, sent


def test_decoded_frames_carry_their_game_time_across_an_encoded_size_change() -> None:
    stream, sent = _stream_of([(64, 48), (32, 24)], 5)
    counts = DecodeCounts()
    out = list(decoded_frames(stream, counts))
    assert [g for g, _ in out] == [2 * 33_333 * (i + 1) for i in range(10)]
    assert counts.decoded == 10 and counts.undecodable == 0
    for (_, picture), original in zip(out, sent, strict=True):
        assert picture.shape == original.shape
        err = np.abs(picture.astype(int) - original.astype(int)).mean()
        assert err < 12, err


def test_a_broken_fragment_or_unknown_frame_is_counted_not_fatal() -> None:
    stream, _ = _stream_of([(64, 48)], 4)
    at, track, _ = stream.fragments[3]
    stream.fragments[3] = (at, track, b"\x00\x00\x00\x08junk")  # the last: no moof
    del stream.frames[2 * 33_333]  # its timing record was lost
    counts = DecodeCounts()
    out = list(decoded_frames(stream, counts))
    assert (counts.decoded, counts.without_game_time, counts.undecodable) == (2, 1, 1)
    assert [g for g, _ in out] == [2 * 33_333, 2 * 3 * 33_333]


def test_a_track_without_its_init_is_skipped() -> None:
    stream, _ = _stream_of([(64, 48)], 2)
    stream.inits.clear()
    counts = DecodeCounts()
    assert list(decoded_frames(stream, counts)) == []
    assert counts.undecodable == 2


def test_avcc_of_an_init_segment_is_the_encoders() -> None:
    encoder = VideoEncoder(EncoderConfig(64, 48, fps=30.0))
    assert avcc_of(encoder.init_segment) == encoder.avc.avcc()


def test_render_to_receive_is_receive_wall_minus_render_wall() -> None:
    stream, _ = _stream_of([(64, 48)], 3)
    assert render_to_receive_ms(stream) == [40.0, 40.0, 40.0]


def test_the_recorder_keeps_video_timing_and_inits_and_ignores_the_rest() -> None:
    recorder = StreamRecorder()
    stream = RecordedStream()
    keep = recorder._keep_timing
    keep(stream, encode_timing({"pts_us": 5, "game_time_us": 9, "stamps": {"render_start": 7}}))
    keep(stream, encode_timing({"pts_us": 6, "stamps": {}}))  # no game time (an X11 source)
    keep(stream, encode_timing({"kind": "audio", "audio_pts_us": 5, "game_time_us": 1}))
    keep(stream, b"not json")
    keep(stream, b"[1, 2]")
    assert stream.frames == {5: (9, 7)}
    init = VideoEncoder(EncoderConfig(64, 48, fps=30.0)).init_segment
    catalog = {
        "video": {
            "renditions": {
                "video1": {
                    "codec": "avc1",
                    "container": {"kind": "cmaf", "init": base64.b64encode(init).decode()},
                }
            }
        }
    }
    with_init = RecordedStream()
    recorder.streams["c"] = with_init
    recorder._follow(_NoLink(), "c", json.dumps(catalog).encode())  # type: ignore[arg-type]
    assert with_init.inits == {"video1": init}
    recorder._follow(_NoLink(), "c", b"{not a catalog")  # type: ignore[arg-type]
    assert with_init.inits == {"video1": init}
    # The video track the catalog named is followed; its frames are kept until stop().
    (subscription,) = [s for s, (b, t) in recorder._video_tracks.items() if b == "c"]
    link = _NoLink()
    recorder.on_events(link, [FrameReceived(subscription, 0, 0, b"frag")])  # type: ignore[arg-type]
    recorder.stop()
    recorder.on_events(link, [FrameReceived(subscription, 1, 0, b"late")])  # type: ignore[arg-type]
    assert [(t, d) for _, t, d in with_init.fragments] == [("video1", b"frag")]
    assert len(recorder.arrivals["c"]) == 2  # the frame count goes on


class _NoSubscribe:
    def __init__(self) -> None:
        self.n = 0

    def subscribe(self, broadcast: str, track: str) -> int:
        self.n += 1
        return self.n

    def unsubscribe(self, subscription: int) -> None:
        pass


class _NoLink:
    def __init__(self) -> None:
        self.moq = _NoSubscribe()

    def flush(self) -> None:
        pass
