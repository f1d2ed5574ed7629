"""VideoEncoder: zero mux delay, decodable CMAF, keyframes, config checks."""

from __future__ import annotations

import io
from typing import Any

import av
import numpy as np
import numpy.typing as npt
import pytest

from server.media.cmaf_read import parse_fragment
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder, default_bitrate

W, H, FPS = 320, 180, 30.0
FRAME_US = round(1e6 / FPS)


def textured(i: int, width: int = W, height: int = H) -> npt.NDArray[np.uint8]:
    """Moving texture: detailed luma, smooth chroma (like real footage, unlike noise)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x = x + 2 * i
    luma = 128 + 60 * np.sin(x / 5.0) * np.cos(y / 7.0) + 30 * np.sin((x + y) / 17.0)
    r = luma + 40 * np.sin(y / 60.0)
    g = luma + 30 * np.cos(x / 80.0)
    b = luma - 40 * np.sin((x - y) / 90.0)
    return np.stack([r, g, b], axis=-1).clip(0, 255).astype(np.uint8)


def psnr(a: npt.NDArray[Any], b: npt.NDArray[np.uint8]) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def decode_all(init: bytes, frames: list[EncodedFrame]) -> list[av.VideoFrame]:
    data = init + b"".join(f.fragment for f in frames)
    with av.open(io.BytesIO(data), mode="r") as container:
        return list(container.decode(video=0))


def test_zero_mux_delay_and_decoded_content() -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_500_000))
    inputs = [textured(i) for i in range(12)]
    # A decoder fed each fragment as it comes out, like the browser: with no
    # decoder delay either, picture i must come out of fragment i.
    live = av.CodecContext.create("h264", "r")
    live.extradata = enc.avc.avcc()
    live.thread_count = 1  # frame threads would add decoder delay
    out: list[EncodedFrame] = []
    for i, rgb in enumerate(inputs):
        if i == 9:  # 300 ms in: past the default 250 ms cooldown after frame 0
            enc.request_keyframe()
        frame = enc.encode(rgb, frame_id=100 + i, pts_us=i * FRAME_US)
        out.append(frame)
        # The call that takes frame i returns frame i's fragment: nothing held back.
        assert enc.frames_in == enc.fragments_out == i + 1
        assert frame.frame_id == 100 + i and frame.pts_us == i * FRAME_US
        info = parse_fragment(frame.fragment)
        assert (info.sequence, info.decode_time, info.keyframe) == (
            i + 1,
            i * FRAME_US,
            frame.keyframe,
        )
        pictures = live.decode(av.Packet(info.sample))
        assert len(pictures) == 1
        assert psnr(pictures[0].to_ndarray(format="rgb24"), rgb) > 30.0
    assert [f.keyframe for f in out] == [i in (0, 9) for i in range(12)]

    decoded = decode_all(enc.init_segment, out)
    assert len(decoded) == len(inputs)
    assert [d.key_frame for d in decoded] == [f.keyframe for f in out]
    assert [d.pts for d in decoded] == [f.pts_us for f in out]
    for d, rgb in zip(decoded, inputs, strict=True):
        assert psnr(d.to_ndarray(format="rgb24"), rgb) > 30.0
    # And each decoded picture is its own input, not a neighbour's.
    assert psnr(decoded[6].to_ndarray(format="rgb24"), inputs[9]) < 25.0


def test_read_only_view_and_strided_input() -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_500_000))
    ro = textured(0)
    ro.flags.writeable = False  # like a view of a ring slot
    crop = textured(1, W + 10, H)[:, 5 : 5 + W]  # rows padded: a linesize, not a copy
    assert not crop.flags.c_contiguous
    out = [enc.encode(ro, 0, 0), enc.encode(crop, 1, FRAME_US)]
    decoded = decode_all(enc.init_segment, out)
    assert psnr(decoded[0].to_ndarray(format="rgb24"), ro) > 30.0
    assert psnr(decoded[1].to_ndarray(format="rgb24"), crop) > 30.0


def test_keyframe_storm_is_coalesced() -> None:
    # 25 fps: 40 ms frames, so the 200 ms interval falls exactly on frame boundaries.
    cfg = EncoderConfig(W, H, fps=25, gop_seconds=100, keyframe_min_interval_ms=200)
    enc = VideoEncoder(cfg)
    keys = []
    for i in range(30):  # a request before every frame
        enc.request_keyframe()
        keys.append(enc.encode(textured(i), i, i * 40_000).keyframe)
    # At most one forced IDR per 200 ms (5 frames), however many requests.
    assert [i for i, k in enumerate(keys) if k] == [0, 5, 10, 15, 20, 25]
    assert enc.forced_keyframes == 6


def test_request_during_cooldown_is_not_lost() -> None:
    cfg = EncoderConfig(W, H, fps=25, gop_seconds=100, keyframe_min_interval_ms=100)
    enc = VideoEncoder(cfg)
    enc.request_keyframe()
    assert enc.encode(textured(0), 0, 0).keyframe
    enc.request_keyframe()  # right after a forced IDR: served at 120 ms, the first frame >= 100
    keys = [enc.encode(textured(i), i, i * 40_000).keyframe for i in range(1, 6)]
    assert keys == [False, False, True, False, False]


def test_periodic_keyframes_follow_gop() -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, gop_seconds=0.2))
    keys = [enc.encode(textured(i), i, i * FRAME_US).keyframe for i in range(13)]
    assert [i for i, k in enumerate(keys) if k] == [0, 6, 12]


def test_periodic_keyframes_keep_their_period_at_a_lower_frame_rate() -> None:
    """Frames at a third of the configured rate (a lowered frame rate): an IDR every
    gop_seconds of stream time, not every keyint frames (which would be 3x as long)."""
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, gop_seconds=0.4))
    keys = [enc.encode(textured(i), i, i * 3 * FRAME_US).keyframe for i in range(13)]
    assert [i for i, k in enumerate(keys) if k] == [0, 4, 8, 12]
    assert enc.periodic_keyframes == 3 and enc.forced_keyframes == 0


def test_codec_string_matches_sps() -> None:
    enc = VideoEncoder(EncoderConfig(1280, 720))
    sps = enc.avc.sps
    assert enc.codec_string() == f"avc1.{sps[1]:02x}{sps[2]:02x}{sps[3]:02x}"
    # ultrafast: constrained baseline; x264 picks level 3.1 for 720p60 at 6 Mbit/s.
    assert enc.codec_string().startswith("avc1.42c0")
    assert sps[3] >= 31


@pytest.mark.parametrize(("width", "height", "field"), [(641, 360, "width"), (640, 361, "height")])
def test_odd_sizes_are_refused(width: int, height: int, field: str) -> None:
    with pytest.raises(ValueError, match=f"{field} must be a positive even number"):
        EncoderConfig(width, height)


def test_wrong_frame_shape_and_pts_are_refused() -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS))
    with pytest.raises(ValueError, match="frame must be uint8"):
        enc.encode(textured(0, W + 2, H), 0, 0)
    enc.encode(textured(0), 0, 1000)
    with pytest.raises(ValueError, match="pts_us must increase"):
        enc.encode(textured(1), 1, 1000)


def test_bad_config_names_the_field() -> None:
    with pytest.raises(ValueError, match="preset must be one of"):
        EncoderConfig(W, H, preset="warp")
    with pytest.raises(ValueError, match="fps must be positive"):
        EncoderConfig(W, H, fps=0)


def test_default_bitrate_scales_with_pixel_rate() -> None:
    assert default_bitrate(1280, 720, 60) == 6_000_000
    assert default_bitrate(1920, 1080, 60) == 13_500_000
    assert default_bitrate(640, 360, 30) == 750_000


def test_request_right_after_periodic_keyframe_waits() -> None:
    cfg = EncoderConfig(W, H, fps=25, gop_seconds=0.4, keyframe_min_interval_ms=100)
    enc = VideoEncoder(cfg)
    keys = []
    for i in range(14):
        if i == 11:  # 40 ms after the periodic IDR at frame 10
            enc.request_keyframe()
        keys.append(enc.encode(textured(i), i, i * 40_000).keyframe)
    assert [i for i, k in enumerate(keys) if k] == [0, 10, 13]  # 13: 120 ms after 10
    assert enc.forced_keyframes == 1


def test_encoded_size_changes_mid_stream_at_an_idr_with_a_new_init_segment() -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_500_000))
    assert enc.encoded_size == (W, H) and enc.encoded_config.generation == 0
    init = enc.init_segment
    first = [enc.encode(textured(i), i, i * FRAME_US) for i in range(4)]
    assert all(f.new_config is None for f in first)
    enc.set_encoded_size(W // 2, H // 2)
    assert enc.encoded_size == (W, H)  # applied by the next encode, on its thread
    second = [enc.encode(textured(i), i, i * FRAME_US) for i in range(4, 10)]
    config = second[0].new_config
    assert config is not None and (config.width, config.height) == (W // 2, H // 2)
    assert config.generation == 1 and enc.encoded_config == config
    assert second[0].keyframe and not any(f.keyframe for f in second[1:])
    assert all(f.new_config is None for f in second[1:])
    # The new track's fragments number from 1; timestamps run on.
    infos = [parse_fragment(f.fragment) for f in second]
    assert [i.sequence for i in infos] == list(range(1, 7))
    assert [i.decode_time for i in infos] == [i * FRAME_US for i in range(4, 10)]
    # Each part decodes with its own init segment, at its own size, and the smaller
    # picture is the input scaled down (area average), not a crop or garbage.
    big = decode_all(init, first)
    small = decode_all(config.init_segment, second)
    assert [(f.width, f.height) for f in big] == [(W, H)] * 4
    assert [(f.width, f.height) for f in small] == [(W // 2, H // 2)] * 6
    reference = textured(9).reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    assert psnr(reference, small[-1].to_ndarray(format="rgb24")) > 28.0
    # A viewer of the new track asks for a keyframe right away: served by the next frame,
    # not after the cooldown (the switch's own IDR went out before anyone subscribed).
    enc.request_keyframe()
    served = enc.encode(textured(10), 10, 10 * FRAME_US + 1000)
    assert served.keyframe and enc.forced_keyframes == 1
    # Asking for the size encoded now is no change; back to full size is generation 2.
    enc.set_encoded_size(W // 2, H // 2)
    assert enc.encode(textured(10), 10, 11 * FRAME_US).new_config is None
    enc.set_encoded_size(W, H)
    back = enc.encode(textured(11), 11, 12 * FRAME_US)
    assert back.keyframe and back.new_config is not None
    assert (back.new_config.generation, back.new_config.width) == (2, W)
    assert enc.size_changes == 2


@pytest.mark.parametrize("size", [(W + 2, H), (W, H + 2), (14, 14), (W - 1, H), (W, H - 3)])
def test_encoded_size_out_of_range_or_odd_is_refused_by_name(size: tuple[int, int]) -> None:
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS))
    with pytest.raises(ValueError, match="encoded size"):
        enc.set_encoded_size(*size)
    # Nothing changed: the next frame is the same size, no new configuration.
    assert enc.encode(textured(0), 0, 0).new_config is None and enc.encoded_size == (W, H)


def test_encoded_size_from_a_scale_is_even_and_bounded() -> None:
    from server.frames.frame import Size
    from server.media.encode import encoded_size

    assert encoded_size(Size(1280, 720), 1.0) == (1280, 720)
    assert encoded_size(Size(1280, 720), 2.0) == (640, 360)
    assert encoded_size(Size(1280, 720), 1.5) == (852, 480)
    assert encoded_size(Size(1278, 718), 3.0) == (426, 238)
    assert encoded_size(Size(64, 36), 4.0) == (16, 16)
    for bad in (0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="encode scale"):
            encoded_size(Size(1280, 720), bad)
