"""CMAF (fragmented MP4) boxes for one H.264 video track, written by hand.

Why by hand: FFmpeg's mov muxer (``frag_every_frame``) writes the fragment of
frame N only when frame N+1 arrives, one frame of added latency, and PyAV does
not expose the muxer flush that ``frag_custom`` would need. The boxes of a
one-sample fragment are small and fixed, so we write them the moment x264
returns the frame's access unit: zero frames of mux delay.

Init segment (the catalog's ``container.init``, base64)::

    ftyp  major "iso6", compatible iso6 cmfc isom avc1 mp41
    moov
      mvhd  v0, timescale, duration 0, next_track_ID 2
      trak
        tkhd  v0, flags 3 (enabled, in movie), track_ID 1, width/height 16.16
        mdia
          mdhd  v0, timescale, duration 0, language "und"
          hdlr  "vide"
          minf
            vmhd  flags 1
            dinf > dref > "url " flags 1 (media in the same file)
            stbl
              stsd > avc1 (width, height) > avcC (SPS/PPS from the encoder)
              stts, stsc, stsz, stco  (empty: samples live in fragments)
      mvex > trex  track_ID 1, sample description 1, no defaults

Media fragment (one per video frame, one MoQ frame)::

    moof
      mfhd  sequence_number (1, 2, ...)
      traf
        tfhd  flags 0x020000 default-base-is-moof, track_ID 1
        tfdt  v1, baseMediaDecodeTime (64-bit: microseconds overflow 32 bits in 71 min)
        trun  flags 0x000701 (data-offset, sample duration, size, flags), 1 sample,
              data_offset = size(moof) + 8 (first byte of the mdat payload)
    mdat  the access unit in AVCC form (4-byte big-endian NAL lengths)

Sample flags: sync 0x02000000 (depends on no other sample), non-sync
0x01010000 (depends on others, sample_is_non_sync_sample). @moq/hang reads the
keyframe bit from ``sample_is_non_sync_sample`` (0x00010000).

There are no B-frames, so decode time = presentation time and no composition
offsets are written.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

TRACK_ID = 1
SYNC_SAMPLE_FLAGS = 0x02000000
NON_SYNC_SAMPLE_FLAGS = 0x01010000

_TFHD_DEFAULT_BASE_IS_MOOF = 0x020000
_TRUN_FLAGS = 0x000001 | 0x000100 | 0x000200 | 0x000400
_NAL_SPS = 7
_NAL_PPS = 8
_UNITY_MATRIX = struct.pack(">9I", 0x00010000, 0, 0, 0, 0x00010000, 0, 0, 0, 0x40000000)


def box(kind: bytes, *payload: bytes) -> bytes:
    """A plain box: 32-bit size, 4-character type, payload."""
    body = b"".join(payload)
    return struct.pack(">I4s", 8 + len(body), kind) + body


def full_box(kind: bytes, version: int, flags: int, *payload: bytes) -> bytes:
    """A full box: a box whose payload starts with version (8 bits) and flags (24 bits)."""
    return box(kind, struct.pack(">I", (version << 24) | flags), *payload)


# --- H.264 parameter sets -------------------------------------------------------------


def split_annexb(data: bytes) -> list[bytes]:
    """NAL units of an Annex-B byte stream, start codes and trailing zeros removed.

    Emulation prevention guarantees 00 00 01 never occurs inside a NAL unit, so a
    plain search is exact. A 4-byte start code leaves a zero at the end of the
    previous unit; a NAL unit never ends in 0x00, so stripping zeros is safe.
    """
    units: list[bytes] = []
    start = data.find(b"\x00\x00\x01")
    while start >= 0:
        begin = start + 3
        nxt = data.find(b"\x00\x00\x01", begin)
        end = len(data) if nxt < 0 else nxt
        unit = data[begin:end].rstrip(b"\x00")
        if unit:
            units.append(unit)
        start = nxt
    return units


def annexb_to_avcc(data: bytes) -> bytes:
    """An Annex-B access unit as MP4 stores it: each NAL unit with a 4-byte length."""
    return b"".join(struct.pack(">I", len(u)) + u for u in split_annexb(data))


@dataclass(frozen=True)
class AvcConfig:
    """SPS and PPS of an H.264 stream: the avcC record and the WebCodecs codec string."""

    sps: bytes
    pps: bytes

    @classmethod
    def from_annexb(cls, extradata: bytes) -> AvcConfig:
        """From x264's global header (Annex-B SPS, PPS and possibly an SEI)."""
        sps = pps = b""
        for unit in split_annexb(extradata):
            kind = unit[0] & 0x1F
            if kind == _NAL_SPS and not sps:
                sps = unit
            elif kind == _NAL_PPS and not pps:
                pps = unit
        if len(sps) < 4 or not pps:
            raise ValueError("encoder extradata has no SPS/PPS (global header flag not set?)")
        return cls(sps, pps)

    @property
    def profile_idc(self) -> int:
        return self.sps[1]

    @property
    def constraint_flags(self) -> int:
        return self.sps[2]

    @property
    def level_idc(self) -> int:
        return self.sps[3]

    def codec_string(self) -> str:
        """RFC 6381 ``avc1.PPCCLL``: profile_idc, constraint flags byte, level_idc in hex."""
        return f"avc1.{self.profile_idc:02x}{self.constraint_flags:02x}{self.level_idc:02x}"

    def avcc(self) -> bytes:
        """AVCDecoderConfigurationRecord (ISO/IEC 14496-15 5.3.3.1), also WebCodecs'
        ``description``. Profiles 100+ would need chroma/bit-depth fields appended;
        the ultrafast preset yields constrained baseline, and decoders accept the
        short form for High too (FFmpeg writes it that way)."""
        return (
            bytes([1, self.profile_idc, self.constraint_flags, self.level_idc])
            + b"\xff"  # 6 reserved bits + lengthSizeMinusOne = 3 (4-byte lengths)
            + b"\xe1"  # 3 reserved bits + one SPS
            + struct.pack(">H", len(self.sps))
            + self.sps
            + b"\x01"  # one PPS
            + struct.pack(">H", len(self.pps))
            + self.pps
        )


# --- Init segment -----------------------------------------------------------------------


def init_segment(width: int, height: int, timescale: int, avc: AvcConfig) -> bytes:
    """ftyp + moov for one H.264 track; see the module docstring for the layout."""
    ftyp = box(b"ftyp", b"iso6", struct.pack(">I", 0), b"iso6cmfcisomavc1mp41")
    mvhd = full_box(
        b"mvhd",
        0,
        0,
        struct.pack(">IIII", 0, 0, timescale, 0),  # creation, modification, timescale, duration
        struct.pack(">IH10x", 0x00010000, 0x0100),  # rate 1.0, volume 1.0, reserved
        _UNITY_MATRIX,
        bytes(24),  # pre_defined
        struct.pack(">I", TRACK_ID + 1),
    )
    tkhd = full_box(
        b"tkhd",
        0,
        0x000003,
        struct.pack(">IIIII", 0, 0, TRACK_ID, 0, 0),  # times, track_ID, reserved, duration
        bytes(8),  # reserved
        struct.pack(">hhhH", 0, 0, 0, 0),  # layer, alternate_group, volume, reserved
        _UNITY_MATRIX,
        struct.pack(">II", width << 16, height << 16),
    )
    mdhd = full_box(
        b"mdhd",
        0,
        0,
        struct.pack(">IIII", 0, 0, timescale, 0),
        struct.pack(">HH", _language_code("und"), 0),
    )
    hdlr = full_box(b"hdlr", 0, 0, bytes(4), b"vide", bytes(12), b"VideoHandler\x00")
    vmhd = full_box(b"vmhd", 0, 1, bytes(8))
    dinf = box(b"dinf", full_box(b"dref", 0, 0, struct.pack(">I", 1), full_box(b"url ", 0, 1)))
    avc1 = box(
        b"avc1",
        bytes(6),  # reserved
        struct.pack(">H", 1),  # data_reference_index
        bytes(16),  # pre_defined, reserved
        struct.pack(">HH", width, height),
        struct.pack(">II", 0x00480000, 0x00480000),  # 72 dpi
        bytes(4),  # reserved
        struct.pack(">H", 1),  # frame_count
        bytes(32),  # compressorname
        struct.pack(">Hh", 0x0018, -1),  # depth, pre_defined
        box(b"avcC", avc.avcc()),
    )
    stbl = box(
        b"stbl",
        full_box(b"stsd", 0, 0, struct.pack(">I", 1), avc1),
        full_box(b"stts", 0, 0, struct.pack(">I", 0)),
        full_box(b"stsc", 0, 0, struct.pack(">I", 0)),
        full_box(b"stsz", 0, 0, struct.pack(">II", 0, 0)),
        full_box(b"stco", 0, 0, struct.pack(">I", 0)),
    )
    minf = box(b"minf", vmhd, dinf, stbl)
    trak = box(b"trak", tkhd, box(b"mdia", mdhd, hdlr, minf))
    trex = full_box(b"trex", 0, 0, struct.pack(">IIIII", TRACK_ID, 1, 0, 0, 0))
    return ftyp + box(b"moov", mvhd, trak, box(b"mvex", trex))


def _language_code(lang: str) -> int:
    """ISO-639-2 packed into 15 bits (three 5-bit letters, offset 0x60)."""
    a, b, c = (ord(ch) - 0x60 for ch in lang)
    return (a << 10) | (b << 5) | c


# --- Media fragments ----------------------------------------------------------------------

# Sizes of the fixed moof of a one-sample fragment, so data_offset is known up front.
_MFHD_SIZE = 16
_TFHD_SIZE = 16
_TFDT_SIZE = 20
_TRUN_SIZE = 12 + 4 + 4 + 12
_TRAF_SIZE = 8 + _TFHD_SIZE + _TFDT_SIZE + _TRUN_SIZE
MOOF_SIZE = 8 + _MFHD_SIZE + _TRAF_SIZE


def media_fragment(
    sequence: int, decode_time: int, duration: int, sample: bytes, keyframe: bool
) -> bytes:
    """moof + mdat carrying one AVCC access unit; times in the init segment's timescale."""
    flags = SYNC_SAMPLE_FLAGS if keyframe else NON_SYNC_SAMPLE_FLAGS
    # One pack call for the whole moof and the mdat header: this runs once per frame.
    header = struct.pack(
        ">I4s" + "I4sII" + "I4s" + "I4sII" + "I4sIQ" + "I4sIIiIII" + "I4s",
        MOOF_SIZE, b"moof",
        _MFHD_SIZE, b"mfhd", 0, sequence,
        _TRAF_SIZE, b"traf",
        _TFHD_SIZE, b"tfhd", _TFHD_DEFAULT_BASE_IS_MOOF, TRACK_ID,
        _TFDT_SIZE, b"tfdt", 1 << 24, decode_time,
        _TRUN_SIZE, b"trun", _TRUN_FLAGS, 1, MOOF_SIZE + 8, duration, len(sample), flags,
        8 + len(sample), b"mdat",
    )  # fmt: skip
    return header + sample


# --- Reading boxes (fragments of any muxer: server/media/cmaf_read.py) ------------------------


@dataclass(frozen=True)
class BoxSpan:
    """Where a box lies in a buffer: ``data[start:end]`` is the whole box."""

    kind: bytes
    start: int
    header: int
    end: int

    @property
    def payload_start(self) -> int:
        return self.start + self.header


def iter_boxes(data: bytes, start: int = 0, end: int | None = None) -> Iterator[BoxSpan]:
    """The boxes laid end to end in ``data[start:end]`` (one level, no descent)."""
    stop = len(data) if end is None else end
    pos = start
    while pos + 8 <= stop:
        size, kind = struct.unpack_from(">I4s", data, pos)
        header = 8
        if size == 1:
            (size,) = struct.unpack_from(">Q", data, pos + 8)
            header = 16
        elif size == 0:
            size = stop - pos
        if size < header or pos + size > stop:
            raise ValueError(f"box {kind!r} at {pos} has bad size {size}")
        yield BoxSpan(kind, pos, header, pos + size)
        pos += size


def find_box(data: bytes, path: list[bytes], start: int = 0, end: int | None = None) -> BoxSpan:
    """The first box along ``path`` (e.g. [b"moof", b"traf", b"trun"]); KeyError if absent."""
    span: BoxSpan | None = None
    for kind in path:
        span = next((b for b in iter_boxes(data, start, end) if b.kind == kind), None)
        if span is None:
            raise KeyError(f"no {kind!r} box")
        start, end = span.payload_start, span.end
    assert span is not None, "path must not be empty"
    return span
