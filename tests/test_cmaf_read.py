"""Reading fragments of any muxer (server/media/cmaf_read.py): FFmpeg's own fragmented MP4
through PyAV with several movflags sets (defaults in tfhd, explicit base offsets,
composition offsets, signed ones in trun v1, several samples per trun, an audio traf
beside the video one), moq-rs's trun layout, the spec's corner cases, and damaged
input (ValueError, never struct.error)."""

from __future__ import annotations

import io
import itertools
import struct
from collections.abc import Iterator

import av
import numpy as np
import pytest

from server.media.cmaf import box, full_box, iter_boxes, media_fragment
from server.media.cmaf_read import FragmentInfo, TrackDefaults, parse_fragment, track_defaults

W, H = 64, 48


def _ffmpeg_fmp4(
    movflags: str, frames: int = 30, bframes: int = 2, audio: bool = False
) -> tuple[bytes, list[tuple[bytes, bool]]]:
    """A fragmented MP4 written by FFmpeg's mov muxer, and the video packets muxed."""
    buf = io.BytesIO()
    out = av.open(buf, "w", format="mp4", options={"movflags": movflags})
    video = out.add_stream("libx264", rate=30)
    video.width, video.height, video.pix_fmt = W, H, "yuv420p"
    video.options = {"preset": "ultrafast", "g": "10", "bf": str(bframes)}
    sound = out.add_stream("aac", rate=48000) if audio else None
    packets: list[tuple[bytes, bool]] = []

    def mux_video(frame: av.VideoFrame | None) -> None:
        for packet in video.encode(frame):
            packets.append((bytes(packet), packet.is_keyframe))
            out.mux(packet)

    pts = 0
    for i in range(frames):
        img = np.zeros((H, W, 3), np.uint8)
        img[:, (i * 2) % W] = 255
        mux_video(av.VideoFrame.from_ndarray(img, format="rgb24"))
        if sound is not None:
            chunk = av.AudioFrame.from_ndarray(
                np.zeros((1, 1600), np.float32), format="fltp", layout="mono"
            )
            chunk.sample_rate, chunk.pts = 48000, pts
            pts += 1600
            for packet in sound.encode(chunk):
                out.mux(packet)
    mux_video(None)
    if sound is not None:
        for packet in sound.encode(None):
            out.mux(packet)
    out.close()
    return buf.getvalue(), packets


def _split(data: bytes) -> tuple[bytes, list[tuple[int, bytes]]]:
    """Init segment (everything before the first moof) and (file offset, moof+mdat)."""
    spans = list(iter_boxes(data))
    first = next(i for i, b in enumerate(spans) if b.kind == b"moof")
    init = data[: spans[first].start]
    fragments = [
        (b.start, data[b.start : spans[i + 1].end])
        for i, b in enumerate(spans)
        if b.kind == b"moof" and i + 1 < len(spans) and spans[i + 1].kind == b"mdat"
    ]
    return init, fragments


def _demuxed(data: bytes) -> list[tuple[bytes, bool, int]]:
    """FFmpeg's own reading of the file: video packets, keyframe flags, decode times."""
    with av.open(io.BytesIO(data)) as container:
        stream = container.streams.video[0]
        return [(bytes(p), p.is_keyframe, int(p.dts)) for p in container.demux(stream) if p.size]


@pytest.mark.parametrize(
    ("movflags", "audio"),
    [
        ("frag_keyframe+empty_moov+default_base_moof", False),  # tfhd 0x20038, trun 0xa05
        ("frag_every_frame+empty_moov", False),  # tfhd base-data-offset 0x39, trun 0x805
        ("frag_keyframe+empty_moov+omit_tfhd_offset", False),  # implicit base: the moof
        ("frag_keyframe+empty_moov+default_base_moof+negative_cts_offsets", False),  # trun v1
        ("frag_keyframe+empty_moov+default_base_moof", True),  # an audio traf beside
        ("frag_keyframe+empty_moov", True),  # two trafs, explicit base offsets
    ],
)
def test_ffmpeg_fragments_give_back_every_packet(movflags: str, audio: bool) -> None:
    data, packets = _ffmpeg_fmp4(movflags, audio=audio)
    init, fragments = _split(data)
    defaults = track_defaults(init)
    assert 1 in defaults
    infos = [parse_fragment(f, defaults, track_id=1, file_offset=at) for at, f in fragments]
    samples = [s for info in infos for s in info.samples]
    demuxed = _demuxed(data)
    assert len(samples) == len(packets) == len(demuxed)
    assert [s.data for s in samples] == [p for p, _, _ in demuxed]
    assert [s.keyframe for s in samples] == [k for _, k, _ in demuxed] == [k for _, k in packets]
    # Decode times run on without a gap across samples and fragments.
    for before, after in itertools.pairwise(samples):
        assert after.decode_time == before.decode_time + before.duration > before.decode_time
    assert infos[0].keyframe and infos[0].decode_time == 0
    if "negative_cts" not in movflags:
        assert any(s.composition_offset > 0 for s in samples)  # B-frames reorder
    # Every fragment decodes by itself from the samples read (keyframe fragments).
    if "frag_keyframe" in movflags:
        codec = av.CodecContext.create("h264", "r")
        codec.extradata = _avcc(init)
        pictures = [p for s in infos[0].samples for p in codec.decode(av.Packet(s.data))]
        pictures += codec.decode(None)
        assert len(pictures) == len(infos[0].samples)


def _avcc(init: bytes) -> bytes:
    at = init.index(b"avcC")
    (size,) = struct.unpack_from(">I", init, at - 4)
    return init[at + 4 : at - 4 + size]


def _fragment(traf_boxes: list[bytes], mdat: bytes, sequence: int = 7) -> bytes:
    moof = box(b"moof", full_box(b"mfhd", 0, 0, struct.pack(">I", sequence)), *traf_boxes)
    return moof + box(b"mdat", mdat)


def _tfdt(t: int) -> bytes:
    return full_box(b"tfdt", 1, 0, struct.pack(">Q", t))


def _moof_size(traf_boxes: list[bytes]) -> int:
    return len(_fragment(traf_boxes, b"")) - 8


def test_moq_rs_trun_layout() -> None:
    """What moq-rs's CMAF importer writes: trun v1 flags 0x305 (data offset, first-sample
    flags, per-sample duration and size), with the durations and sizes of 3 samples."""
    payloads = [b"K" * 5, b"p" * 3, b"q" * 4]

    def traf(offset: int) -> bytes:
        trun = full_box(
            b"trun", 1, 0x305, struct.pack(">IiI", 3, offset, 0x02000000),
            *(struct.pack(">II", 1000, len(p)) for p in payloads),
        )  # fmt: skip
        return box(
            b"traf", full_box(b"tfhd", 0, 0x020000, struct.pack(">I", 1)), _tfdt(90_000), trun
        )

    offset = _moof_size([traf(0)]) + 8
    info = parse_fragment(_fragment([traf(offset)], b"".join(payloads)))
    assert [s.data for s in info.samples] == payloads
    assert [s.decode_time for s in info.samples] == [90_000, 91_000, 92_000]
    assert info.keyframe and info.sequence == 7 and info.sample == payloads[0]


def test_defaults_from_tfhd_and_trex_and_truns_without_offsets() -> None:
    """Sizes from tfhd, durations and flags from trex; the second trun continues where
    the first ended; a second traf (track 2) without a base continues after the first."""
    a, b, c = b"A" * 4, b"B" * 4, b"C" * 6
    tfhd1 = full_box(b"tfhd", 0, 0x000010, struct.pack(">II", 1, 4))  # default size 4
    trun1 = full_box(b"trun", 0, 0x000001, struct.pack(">Ii", 1, 0))  # patched below
    trun2 = full_box(b"trun", 0, 0x000000, struct.pack(">I", 1))  # continues
    tfhd2 = full_box(b"tfhd", 0, 0x000010, struct.pack(">II", 2, 6))
    trun3 = full_box(b"trun", 0, 0x000000, struct.pack(">I", 1))
    trafs = [box(b"traf", tfhd1, _tfdt(50), trun1, trun2), box(b"traf", tfhd2, _tfdt(9), trun3)]
    offset = _moof_size(trafs) + 8
    trafs[0] = box(
        b"traf", tfhd1, _tfdt(50), full_box(b"trun", 0, 1, struct.pack(">Ii", 1, offset)), trun2
    )
    data = _fragment(trafs, a + b + c)
    defaults = {1: TrackDefaults(duration=20, flags=0x01010000), 2: TrackDefaults(duration=3)}
    video = parse_fragment(data, defaults)
    assert [s.data for s in video.samples] == [a, b]
    assert [s.decode_time for s in video.samples] == [50, 70]
    assert not video.keyframe  # trex flags: non-sync
    other = parse_fragment(data, defaults, track_id=2)
    assert other.sample == c and other.keyframe and other.duration == 3


def test_base_data_offset_and_duration_is_empty() -> None:
    payload = b"X" * 9
    tfhd = full_box(b"tfhd", 0, 0x000001 | 0x000008, struct.pack(">IQI", 1, 0, 33))
    trun = full_box(b"trun", 0, 0x000201, struct.pack(">IiI", 1, 0, len(payload)))
    probe = _fragment([box(b"traf", tfhd, _tfdt(0), trun)], payload)
    at = probe.index(payload)  # base 0 = the buffer's start, offset = where mdat's data is
    trun = full_box(b"trun", 0, 0x000201, struct.pack(">IiI", 1, at, len(payload)))
    info = parse_fragment(_fragment([box(b"traf", tfhd, _tfdt(66), trun)], payload))
    assert info.sample == payload and info.duration == 33 and info.decode_time == 66
    empty_tfhd = full_box(b"tfhd", 0, 0x010000 | 0x020000, struct.pack(">I", 1))
    empty = parse_fragment(_fragment([box(b"traf", empty_tfhd, _tfdt(5))], b""))
    assert empty.samples == () and empty.decode_time == 5 and empty.sample == b""


def test_upcasts_own_fragments_still_read() -> None:
    frag = media_fragment(3, 1234, 33, b"\x00\x00\x00\x01\x65", keyframe=False)
    info = parse_fragment(frag)
    assert (info.sequence, info.decode_time, info.duration, info.keyframe) == (3, 1234, 33, False)
    assert info.sample == b"\x00\x00\x00\x01\x65"


def _damaged(frag: bytes) -> Iterator[bytes]:
    for cut in range(len(frag)):
        yield frag[:cut]
    for at in range(0, len(frag), 3):
        yield frag[:at] + bytes([frag[at] ^ 0xFF]) + frag[at + 1 :]


def test_damage_is_a_value_error() -> None:
    frag = media_fragment(1, 0, 33, b"\x01\x02\x03\x04", keyframe=True)
    for bad in _damaged(frag):
        try:
            result = parse_fragment(bad)
        except ValueError:
            continue
        assert isinstance(result, FragmentInfo)  # a flipped byte in the payload is fine
