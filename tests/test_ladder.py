"""The rendition ladder: rung sizes and rates, aligned IDRs, decodable scaled pictures,
a failing rung dropped while the others go on, and the catalog listing every rung."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import numpy.typing as npt
import pytest

from server.frames.frame import Size
from server.media.catalog import catalog_of, is_rung_track, rung_track_name
from server.media.cmaf_read import parse_fragment
from server.media.encode import EncoderConfig, VideoEncoder
from server.media.ladder import RenditionLadder
from server.stream_config import parse_divisors
from tests.test_encode_catalog import HANG_MISSING, HANG_REASON, run_with_hang

DISPLAY = Size(640, 360)
FPS = 30.0
FRAME_US = 33_333


def scene(index: int) -> npt.NDArray[np.uint8]:
    """A moving diagonal gradient with a bright square: detail a scaler must keep."""
    y, x = np.mgrid[0 : DISPLAY.height, 0 : DISPLAY.width]
    frame = np.empty((DISPLAY.height, DISPLAY.width, 3), np.uint8)
    frame[..., 0] = (x + 3 * index) % 256
    frame[..., 1] = (y * 2) % 256
    frame[..., 2] = ((x + y) // 2) % 256
    left = 40 + 4 * index
    frame[100:180, left : left + 80] = 250
    return frame


def test_divisors_parse_and_refuse_what_makes_no_rung() -> None:
    assert parse_divisors("4,2") == (2, 4)
    assert parse_divisors("off") == () == parse_divisors("")
    for bad, word in (("1", "at least 2"), ("2,2", "differ"), ("a", "divisors like"),
                      ("2,3,4,5,6", "at most")):  # fmt: skip
        with pytest.raises(ValueError, match=word):
            parse_divisors(bad)


def test_rung_names_say_their_size_and_are_not_player_tracks() -> None:
    assert rung_track_name(640, 360) == "video.640x360"
    assert is_rung_track("video.640x360")
    for name in ("video", "video.1", "video.x360", "audio.640x360", "video.640x"):
        assert not is_rung_track(name), name


def test_rungs_have_the_divided_sizes_and_rates_below_the_players() -> None:
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4))
    sizes = [(r.track, r.width, r.height) for r in ladder.rungs]
    assert sizes == [("video.320x180", 320, 180), ("video.160x90", 160, 90)]
    rates = [r.bitrate for r in ladder.rungs]
    assert rates[0] > rates[1] >= 100_000
    renditions = ladder.renditions()
    assert list(renditions) == ["video.320x180", "video.160x90"]
    assert renditions["video.320x180"].coded_width == 320


def test_idrs_come_every_gop_on_the_same_frames_and_at_the_players_idrs() -> None:
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4), gop_seconds=1.0)
    keyframes: dict[str, list[int]] = {t: [] for t in ladder.tracks}
    for i in range(70):
        align = i == 40  # the player's track made an IDR here (a viewer asked it)
        if i == 50:
            ladder.request_keyframe()  # honoured: 300 ms after the last IDR
        if i == 52:
            ladder.request_keyframe()  # within 250 ms of that one: waits for frame 58
        frames, failed = ladder.encode(scene(i), i, 1_000_000 + i * FRAME_US, align=align)
        assert failed == []
        assert [f.track for f in frames] == list(ladder.tracks)
        for f in frames:
            assert f.encoded.frame_id == i
            if f.encoded.keyframe:
                keyframes[f.track].append(i)
    expected = [0, 30, 40, 50, 58]
    assert all(k == expected for k in keyframes.values()), keyframes
    assert ladder.stats.aligned_keyframes == 1 and ladder.stats.requested_keyframes == 2


def decode(config_init: bytes, fragments: list[bytes], avcc: bytes) -> list[npt.NDArray[np.uint8]]:
    codec = av.CodecContext.create("h264", "r")
    codec.extradata = avcc
    pictures = []
    for fragment in fragments:
        info = parse_fragment(fragment)
        for frame in codec.decode(av.Packet(info.sample)):
            pictures.append(frame.to_ndarray(format="rgb24"))
    return pictures


def test_a_rung_shows_the_frame_scaled_down() -> None:
    ladder = RenditionLadder(DISPLAY, FPS, (2,))
    rung = ladder.rungs[0]
    fragments = []
    for i in range(5):
        frames, _ = ladder.encode(scene(i), i, 1_000_000 + i * FRAME_US)
        fragments.append(frames[0].encoded.fragment)
    pictures = decode(rung.encoder.init_segment, fragments, rung.encoder.avc.avcc())
    assert len(pictures) == 5
    shown = pictures[-1].astype(np.float64)
    assert shown.shape == (180, 320, 3)

    # The reference: the display frame averaged over 2x2 blocks (what area scaling does).
    def psnr_against(index: int) -> float:
        full = scene(index).astype(np.float64)
        reference = full.reshape(180, 2, 320, 2, 3).mean(axis=(1, 3))
        return float(10 * np.log10(255**2 / np.mean((shown - reference) ** 2)))

    # A rung at its low rate loses detail (the gradient's wraps are hard edges), but it
    # shows this frame: an older frame (the square 16 px to the left) matches far worse.
    assert psnr_against(4) > 25
    assert psnr_against(4) > psnr_against(0) + 5


def test_a_failing_rung_is_dropped_and_the_others_go_on(monkeypatch: pytest.MonkeyPatch) -> None:
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4))
    broken = ladder.rungs[0]

    def fail(*_args: object, **_kwargs: object) -> None:
        raise RuntimeError("encoder gone")

    monkeypatch.setattr(broken.encoder, "encode_yuv", fail)
    frames, failed = ladder.encode(scene(0), 0, 1_000_000)
    assert failed == [broken.track]
    assert [f.track for f in frames] == ["video.160x90"]
    assert ladder.tracks == ("video.160x90",)
    frames, failed = ladder.encode(scene(1), 1, 1_000_000 + FRAME_US)
    assert failed == [] and [f.track for f in frames] == ["video.160x90"]
    assert ladder.stats.failed_rungs == [broken.track]


def test_a_tiny_display_keeps_only_distinct_rungs() -> None:
    ladder = RenditionLadder(Size(32, 32), FPS, (2, 4))
    # 16x16 is the smallest size x264 and browsers take: both divisors land on it.
    assert ladder.tracks == ("video.16x16",)


def test_catalog_lists_the_players_track_first_then_the_rungs() -> None:
    player = VideoEncoder(EncoderConfig(DISPLAY.width, DISPLAY.height, fps=FPS))
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4))
    catalog = json.loads(
        catalog_of(player.encoded_config, FPS, 2_000_000, rungs=ladder.renditions()).to_json()
    )
    renditions = catalog["video"]["renditions"]
    assert list(renditions) == ["video", "video.320x180", "video.160x90"]
    assert renditions["video.160x90"]["codedHeight"] == 90
    assert renditions["video.320x180"]["bitrate"] == ladder.rungs[0].bitrate


_HANG_LADDER_JS = """
import { readFileSync } from "node:fs";
import * as Catalog from "HANG/catalog/index.js";
import * as Cmaf from "HANG/container/cmaf/decode.js";
const parsed = Catalog.RootSchema.parse(JSON.parse(readFileSync(process.argv[2], "utf8")));
const out = {};
for (const [track, r] of Object.entries(parsed.video.renditions)) {
  const init = Cmaf.decodeInitSegment(new Uint8Array(Buffer.from(r.container.init, "base64")));
  out[track] = [r.codedWidth, r.codedHeight, init.timescale];
}
console.log(JSON.stringify(out));
"""


@pytest.mark.skipif(HANG_MISSING, reason=HANG_REASON)
def test_hang_accepts_the_ladder_catalog(tmp_path: Path) -> None:
    player = VideoEncoder(EncoderConfig(DISPLAY.width, DISPLAY.height, fps=FPS))
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4))
    path = tmp_path / "catalog.json"
    path.write_bytes(
        catalog_of(player.encoded_config, FPS, None, rungs=ladder.renditions()).to_json()
    )
    out = run_with_hang(tmp_path, _HANG_LADDER_JS, path)
    assert out == {
        "video": [640, 360, 1_000_000],
        "video.320x180": [320, 180, 1_000_000],
        "video.160x90": [160, 90, 1_000_000],
    }


def test_the_players_yuv_frame_gives_the_rungs_the_same_pictures_as_rgb() -> None:
    player = VideoEncoder(EncoderConfig(DISPLAY.width, DISPLAY.height, fps=FPS))
    from_rgb = RenditionLadder(DISPLAY, FPS, (2, 4))
    from_yuv = RenditionLadder(DISPLAY, FPS, (2, 4))
    rgb_fragments: list[bytes] = []
    yuv_fragments: list[bytes] = []
    for i in range(4):
        pts = 1_000_000 + i * FRAME_US
        player.encode(scene(i), i, pts)
        assert player.last_yuv is not None
        rgb_fragments += [f.encoded.fragment for f in from_rgb.encode(scene(i), i, pts)[0]]
        yuv_fragments += [f.encoded.fragment for f in from_yuv.encode(player.last_yuv, i, pts)[0]]
    # One conversion either way (the same swscale call): the same bytes out.
    assert rgb_fragments == yuv_fragments
    assert from_yuv.stats.convert_cpu_s == 0.0 < from_rgb.stats.convert_cpu_s


def test_a_frame_of_the_wrong_size_is_refused_with_its_size() -> None:
    small = VideoEncoder(EncoderConfig(320, 180, fps=FPS))
    small.encode(np.zeros((180, 320, 3), np.uint8), 0, 0)
    ladder = RenditionLadder(DISPLAY, FPS, (2,))
    assert small.last_yuv is not None
    with pytest.raises(ValueError, match="yuv420p 640x360, got yuv420p 320x180"):
        ladder.encode(small.last_yuv, 0, 0)
    with pytest.raises(ValueError, match="yuv420p 320x180"):
        ladder.rungs[0].encoder.encode_yuv(small.last_yuv.reformat(width=64, height=36), 0, 0)


def test_only_watched_rungs_are_encoded_and_a_resumed_one_starts_at_an_idr() -> None:
    ladder = RenditionLadder(DISPLAY, FPS, (2, 4), gop_seconds=10.0)
    ladder.set_wanted(frozenset())
    assert ladder.idle
    frames, _ = ladder.encode(scene(0), 0, 1_000_000)
    assert frames == [] and ladder.stats.idle_frames == 1
    # Only the small rung is watched: the big one scales (the small one comes from it)
    # but encodes nothing.
    ladder.set_wanted(frozenset({"video.160x90"}))
    ladder.request_keyframe()  # what a new subscription asks
    frames, _ = ladder.encode(scene(1), 1, 1_000_000 + FRAME_US)
    assert [(f.track, f.encoded.keyframe) for f in frames] == [("video.160x90", True)]
    frames, _ = ladder.encode(scene(2), 2, 1_000_000 + 2 * FRAME_US)
    assert [(f.track, f.encoded.keyframe) for f in frames] == [("video.160x90", False)]
    assert ladder.rungs[0].frames == 0 and ladder.rungs[1].frames == 2
    ladder.set_wanted(None)  # every rung (the benchmark's case)
    assert not ladder.idle
