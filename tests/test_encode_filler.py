"""Filler data: the session's link probe makes frames larger without changing a pixel."""

from __future__ import annotations

import av
import numpy as np
import pytest

from server.media.cmaf_read import parse_fragment
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder
from server.media.filler import MIN_FILLER_BYTES, NAL_FILLER, filler_nal, pad_sample
from tests.test_encode import FPS, FRAME_US, H, W, decode_all, textured


def encode_run(floors: list[int]) -> tuple[VideoEncoder, list[EncodedFrame]]:
    # One x264 thread: its output is then the same run to run, so the padded and the
    # plain stream can be compared byte for byte.
    enc = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_000_000, threads=1))
    frames = []
    for i, floor in enumerate(floors):
        enc.pad_frames_to(floor)
        frames.append(enc.encode(textured(i), frame_id=i, pts_us=i * FRAME_US))
    return enc, frames


def test_padded_frames_reach_the_size_and_decode_to_the_same_pictures() -> None:
    floors = [0, 0, 40_000, 40_000, 0, 9_000, 9_000, 0]
    plain_enc, plain = encode_run([0] * len(floors))
    padded_enc, padded = encode_run(floors)
    for frame, reference, floor in zip(padded, plain, floors, strict=True):
        assert frame.padded_to == floor
        if floor > len(reference.fragment):
            assert len(frame.fragment) == floor  # exactly the size asked, not more
            assert frame.filler_bytes == floor - len(reference.fragment)
        else:
            assert frame.fragment == reference.fragment and frame.filler_bytes == 0
        # The sample in the fragment is x264's access unit, then one filler NAL unit.
        info = parse_fragment(frame.fragment)
        assert (
            len(info.sample) == len(parse_fragment(reference.fragment).sample) + frame.filler_bytes
        )
    assert any(f.filler_bytes > 0 for f in padded)
    # A decoder reads past the filler: every picture is bit-identical to the unpadded
    # stream's (the catalog's decoder, FFmpeg's h264, as in the browser).
    for a, b in zip(
        decode_all(padded_enc.init_segment, padded),
        decode_all(plain_enc.init_segment, plain),
        strict=True,
    ):
        assert np.array_equal(a.to_ndarray(format="yuv420p"), b.to_ndarray(format="yuv420p"))


def test_a_live_decoder_fed_padded_fragments_one_by_one_shows_each_picture() -> None:
    enc, frames = encode_run([30_000] * 6)
    live = av.CodecContext.create("h264", "r")
    live.extradata = enc.avc.avcc()
    live.thread_count = 1
    for frame in frames:
        assert len(live.decode(av.Packet(parse_fragment(frame.fragment).sample))) == 1


def test_filler_nal_layout() -> None:
    nal = filler_nal(10)
    assert len(nal) == 10
    assert int.from_bytes(nal[:4], "big") == 6  # the AVCC length counts the rest
    assert nal[4] & 0x1F == NAL_FILLER and nal[4] & 0x80 == 0
    assert nal[5:-1] == b"\xff" * 4 and nal[-1] == 0x80
    assert len(filler_nal(MIN_FILLER_BYTES)) == MIN_FILLER_BYTES
    with pytest.raises(ValueError, match="at least"):
        filler_nal(MIN_FILLER_BYTES - 1)
    # Too small a gap to fill, or none: the sample is untouched.
    assert pad_sample(b"x" * 100, 100 + MIN_FILLER_BYTES - 1) == b"x" * 100
    assert pad_sample(b"x" * 100, 50) == b"x" * 100
    assert len(pad_sample(b"x" * 100, 100 + MIN_FILLER_BYTES)) == 100 + MIN_FILLER_BYTES
