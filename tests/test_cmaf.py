"""fMP4 box writing and reading (server/media/cmaf.py), without an encoder."""

from __future__ import annotations

import struct

import pytest

from server.media.cmaf import (
    MOOF_SIZE,
    NON_SYNC_SAMPLE_FLAGS,
    SYNC_SAMPLE_FLAGS,
    AvcConfig,
    annexb_to_avcc,
    find_box,
    init_segment,
    iter_boxes,
    media_fragment,
    split_annexb,
)
from server.media.cmaf_read import parse_fragment

# A real x264 global header: constrained baseline (0x42, 0xc0), level 3.1 (0x1f).
SPS = bytes.fromhex("6742c01fda0280bfe59a808080a0000003002000000f11e30654")
PPS = bytes.fromhex("68ce3c80")


def test_split_annexb_handles_3_and_4_byte_start_codes() -> None:
    stream = b"\x00\x00\x00\x01" + SPS + b"\x00\x00\x01" + PPS + b"\x00\x00\x00\x01\x65\x88\x84"
    assert split_annexb(stream) == [SPS, PPS, b"\x65\x88\x84"]
    avcc = annexb_to_avcc(stream)
    assert avcc[:4] == struct.pack(">I", len(SPS))
    assert avcc.endswith(struct.pack(">I", 3) + b"\x65\x88\x84")


def test_avc_config_codec_string_and_avcc() -> None:
    avc = AvcConfig.from_annexb(b"\x00\x00\x00\x01" + SPS + b"\x00\x00\x00\x01" + PPS)
    assert avc.codec_string() == "avc1.42c01f"
    record = avc.avcc()
    assert record[:4] == bytes([1, 0x42, 0xC0, 0x1F])
    assert record[4] == 0xFF  # 4-byte NAL lengths
    assert record[5] == 0xE1  # one SPS
    assert record[6 : 8 + len(SPS)] == struct.pack(">H", len(SPS)) + SPS
    assert record.endswith(b"\x01" + struct.pack(">H", len(PPS)) + PPS)


def test_avc_config_without_parameter_sets_is_refused() -> None:
    with pytest.raises(ValueError, match="SPS/PPS"):
        AvcConfig.from_annexb(b"\x00\x00\x01\x65\x88")


def test_init_segment_layout() -> None:
    init = init_segment(1280, 720, 1_000_000, AvcConfig(SPS, PPS))
    assert [b.kind for b in iter_boxes(init)] == [b"ftyp", b"moov"]
    moov = find_box(init, [b"moov"])
    assert [b.kind for b in iter_boxes(init, moov.payload_start, moov.end)] == [
        b"mvhd",
        b"trak",
        b"mvex",
    ]
    mdhd = find_box(init, [b"moov", b"trak", b"mdia", b"mdhd"])
    (timescale,) = struct.unpack_from(">I", init, mdhd.payload_start + 12)
    assert timescale == 1_000_000
    stsd = find_box(init, [b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stsd"])
    avc1 = next(iter_boxes(init, stsd.payload_start + 8, stsd.end))
    assert avc1.kind == b"avc1"
    assert struct.unpack_from(">HH", init, avc1.payload_start + 24) == (1280, 720)
    avcc = find_box(init, [b"avcC"], avc1.payload_start + 78, avc1.end)
    assert init[avcc.payload_start : avcc.end] == AvcConfig(SPS, PPS).avcc()
    trex = find_box(init, [b"moov", b"mvex", b"trex"])
    assert struct.unpack_from(">II", init, trex.payload_start + 4) == (1, 1)


@pytest.mark.parametrize("keyframe", [True, False])
def test_media_fragment_round_trip(keyframe: bool) -> None:
    sample = b"\x00\x00\x00\x03\x65\x88\x84"
    frag = media_fragment(7, 5_000_000_000, 16_667, sample, keyframe)
    assert [b.kind for b in iter_boxes(frag)] == [b"moof", b"mdat"]
    moof = find_box(frag, [b"moof"])
    assert moof.end == MOOF_SIZE
    assert frag[MOOF_SIZE + 8 :] == sample
    trun = find_box(frag, [b"moof", b"traf", b"trun"])
    (offset,) = struct.unpack_from(">i", frag, trun.payload_start + 8)
    assert offset == MOOF_SIZE + 8  # data offset relative to moof (default-base-is-moof)
    (flags,) = struct.unpack_from(">I", frag, trun.end - 4)
    assert flags == (SYNC_SAMPLE_FLAGS if keyframe else NON_SYNC_SAMPLE_FLAGS)
    info = parse_fragment(frag)
    assert (info.sequence, info.decode_time, info.duration) == (7, 5_000_000_000, 16_667)
    assert info.keyframe is keyframe
    assert info.sample == sample


def test_bad_box_size_is_an_error() -> None:
    with pytest.raises(ValueError, match="bad size"):
        list(iter_boxes(struct.pack(">I4s", 100, b"moof")))
