"""Reading CMAF / fragmented MP4 media fragments written by any muxer (ISO/IEC 14496-12).

``server/media/cmaf.py`` writes one fixed layout (one sample, default-base-is-moof, trun
flags 0x701); other publishers do not: moq-rs's CMAF importer writes trun flags
0x1000305 (version 1, sample flags and composition offsets), FFmpeg's mov muxer
puts defaults in tfhd and several samples in one trun, and a fragment may carry
several trafs or truns. This reader follows the specification instead:

- tfhd: base-data-offset (0x1), sample-description-index (0x2), default sample
  duration/size/flags (0x8/0x10/0x20), duration-is-empty (0x10000),
  default-base-is-moof (0x20000); missing defaults fall back to the init
  segment's trex (``track_defaults``), then to 0.
- trun: data-offset (0x1), first-sample-flags (0x4), per-sample duration,
  size, flags and composition offset (0x100/0x200/0x400/0x800); version 1
  composition offsets are signed.
- Data offsets: relative to base-data-offset if given, else to the moof with
  default-base-is-moof or for the first traf, else to the end of the previous
  traf's data; a trun without data-offset continues where the previous one
  ended. Every sample must lie inside an mdat of the buffer.
- The decode time of each sample: tfdt's baseMediaDecodeTime (CMAF requires tfdt)
  plus the durations before it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from server.media.cmaf import BoxSpan, iter_boxes

# Bits of sample_flags: sample_is_non_sync_sample, and sample_depends_on == 1.
_NON_SYNC_BIT = 0x00010000

_TFHD_BASE_DATA_OFFSET = 0x000001
_TFHD_SAMPLE_DESCRIPTION_INDEX = 0x000002
_TFHD_DEFAULT_DURATION = 0x000008
_TFHD_DEFAULT_SIZE = 0x000010
_TFHD_DEFAULT_FLAGS = 0x000020
_TFHD_DURATION_IS_EMPTY = 0x010000
_TFHD_DEFAULT_BASE_IS_MOOF = 0x020000

_TRUN_DATA_OFFSET = 0x000001
_TRUN_FIRST_SAMPLE_FLAGS = 0x000004
_TRUN_DURATION = 0x000100
_TRUN_SIZE = 0x000200
_TRUN_FLAGS = 0x000400
_TRUN_COMPOSITION_OFFSET = 0x000800


@dataclass(frozen=True)
class TrackDefaults:
    """A trex box: what a fragment's samples are when neither tfhd nor trun says."""

    sample_description_index: int = 1
    duration: int = 0
    size: int = 0
    flags: int = 0


@dataclass(frozen=True)
class Sample:
    decode_time: int
    duration: int
    composition_offset: int
    keyframe: bool
    data: bytes


@dataclass(frozen=True)
class FragmentInfo:
    """One moof + mdat: the samples of one track (the first traf's unless chosen).

    ``decode_time``, ``duration``, ``keyframe`` and ``sample`` describe the first
    sample (a fragment of upcast's own carries one); ``decode_time`` is tfdt's
    even when the fragment is empty (duration-is-empty)."""

    sequence: int
    track_id: int
    decode_time: int
    samples: tuple[Sample, ...]

    @property
    def duration(self) -> int:
        return self.samples[0].duration if self.samples else 0

    @property
    def keyframe(self) -> bool:
        return bool(self.samples) and self.samples[0].keyframe

    @property
    def sample(self) -> bytes:
        return self.samples[0].data if self.samples else b""


def _children(data: bytes, span: BoxSpan) -> list[BoxSpan]:
    return list(iter_boxes(data, span.payload_start, span.end))


def track_defaults(init: bytes) -> dict[int, TrackDefaults]:
    """The trex defaults of each track in an init segment (moov > mvex > trex)."""
    found: dict[int, TrackDefaults] = {}
    for moov in (b for b in iter_boxes(init) if b.kind == b"moov"):
        for mvex in (b for b in _children(init, moov) if b.kind == b"mvex"):
            for trex in (b for b in _children(init, mvex) if b.kind == b"trex"):
                track, index, duration, size, flags = struct.unpack_from(
                    ">IIIII", init, trex.payload_start + 4
                )
                found[track] = TrackDefaults(index, duration, size, flags)
    return found


def track_timescales(init: bytes) -> dict[int, int]:
    """Each track's media timescale (ticks per second) in an init segment: tkhd's
    track_ID and mdhd's timescale of every moov > trak."""
    found: dict[int, int] = {}
    for moov in (b for b in iter_boxes(init) if b.kind == b"moov"):
        for trak in (b for b in _children(init, moov) if b.kind == b"trak"):
            boxes = _children(init, trak)
            tkhd = next((b for b in boxes if b.kind == b"tkhd"), None)
            mdia = next((b for b in boxes if b.kind == b"mdia"), None)
            mdhd = (
                None
                if mdia is None
                else next((b for b in _children(init, mdia) if b.kind == b"mdhd"), None)
            )
            if tkhd is None or mdhd is None:
                continue
            version, _, cur = _full_box(init, tkhd)
            cur.take(">QQ" if version == 1 else ">II")  # creation, modification times
            track = cur.one(">I")
            version, _, cur = _full_box(init, mdhd)
            cur.take(">QQ" if version == 1 else ">II")
            found[track] = cur.one(">I")
    return found


@dataclass
class _Cursor:
    """Reads big-endian fields from a box payload, refusing to run past its end."""

    data: bytes
    pos: int
    end: int

    def take(self, fmt: str) -> tuple[int, ...]:
        size = struct.calcsize(fmt)
        if self.pos + size > self.end:
            raise ValueError(f"box too short for its flags at {self.pos}")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def one(self, fmt: str) -> int:
        return self.take(fmt)[0]


def _full_box(data: bytes, span: BoxSpan) -> tuple[int, int, _Cursor]:
    cursor = _Cursor(data, span.payload_start, span.end)
    word = cursor.one(">I")
    return word >> 24, word & 0xFFFFFF, cursor


def parse_fragment(
    data: bytes,
    defaults: dict[int, TrackDefaults] | None = None,
    track_id: int | None = None,
    file_offset: int = 0,
) -> FragmentInfo:
    """The samples of ``track_id`` (default: the first traf's track) in a moof + mdat.

    ``defaults``: the init segment's ``track_defaults``, needed only when a fragment
    leaves a sample's size, duration or flags to trex. ``file_offset``: where ``data``
    starts in its file, for a tfhd base-data-offset (an absolute file position; CMAF
    itself forbids it, FFmpeg without default_base_moof writes it). Raises ValueError
    on a malformed fragment (struct.error never escapes)."""
    top = list(iter_boxes(data))
    moof = next((b for b in top if b.kind == b"moof"), None)
    if moof is None:
        raise ValueError("no moof box")
    mdats = [(b.payload_start, b.end) for b in top if b.kind == b"mdat"]
    sequence = 0
    chosen: FragmentInfo | None = None
    previous_data_end = moof.start  # the implicit base of a traf without one
    for child in _children(data, moof):
        if child.kind == b"mfhd":
            sequence = _full_box(data, child)[2].one(">I")
        elif child.kind == b"traf":
            info, previous_data_end = _read_traf(
                data, child, (moof.start, previous_data_end, file_offset), sequence,
                defaults or {}, mdats,
            )  # fmt: skip
            if chosen is None and (track_id is None or info.track_id == track_id):
                chosen = info
    if chosen is None:
        raise ValueError("no traf" if track_id is None else f"no traf for track {track_id}")
    return chosen


def _read_traf(
    data: bytes,
    traf: BoxSpan,
    bases: tuple[int, int, int],
    sequence: int,
    defaults: dict[int, TrackDefaults],
    mdats: list[tuple[int, int]],
) -> tuple[FragmentInfo, int]:
    boxes = _children(data, traf)
    tfhd = next((b for b in boxes if b.kind == b"tfhd"), None)
    if tfhd is None:
        raise ValueError("traf without tfhd")
    moof_start, previous_data_end, file_offset = bases
    _, flags, cur = _full_box(data, tfhd)
    track = cur.one(">I")
    trex = defaults.get(track, TrackDefaults())
    base = cur.one(">Q") - file_offset if flags & _TFHD_BASE_DATA_OFFSET else None
    if flags & _TFHD_SAMPLE_DESCRIPTION_INDEX:
        cur.one(">I")
    default_duration = cur.one(">I") if flags & _TFHD_DEFAULT_DURATION else trex.duration
    default_size = cur.one(">I") if flags & _TFHD_DEFAULT_SIZE else trex.size
    default_flags = cur.one(">I") if flags & _TFHD_DEFAULT_FLAGS else trex.flags
    if base is None:
        base = moof_start if flags & _TFHD_DEFAULT_BASE_IS_MOOF else previous_data_end

    tfdt = next((b for b in boxes if b.kind == b"tfdt"), None)
    if tfdt is None:
        raise ValueError("traf without tfdt (CMAF requires baseMediaDecodeTime)")
    version, _, cur = _full_box(data, tfdt)
    decode_time = cur.one(">Q" if version == 1 else ">I")

    samples: list[Sample] = []
    position = base
    clock = decode_time
    truns = [b for b in boxes if b.kind == b"trun"]
    if flags & _TFHD_DURATION_IS_EMPTY and truns:
        raise ValueError("tfhd says duration-is-empty but the traf has a trun")
    for trun in truns:
        version, tflags, cur = _full_box(data, trun)
        count = cur.one(">I")
        if tflags & _TRUN_DATA_OFFSET:
            position = base + cur.one(">i")
        first_flags = cur.one(">I") if tflags & _TRUN_FIRST_SAMPLE_FLAGS else None
        per_sample = [
            (bit, fmt)
            for bit, fmt in (
                (_TRUN_DURATION, "I"),
                (_TRUN_SIZE, "I"),
                (_TRUN_FLAGS, "I"),
                (_TRUN_COMPOSITION_OFFSET, "i" if version >= 1 else "I"),
            )
            if tflags & bit
        ]
        row = ">" + "".join(fmt for _, fmt in per_sample)
        if count * struct.calcsize(row) > cur.end - cur.pos:
            raise ValueError(f"trun claims {count} samples, more than the box holds")
        for i in range(count):
            values = dict(zip((bit for bit, _ in per_sample), cur.take(row), strict=True))
            duration = values.get(_TRUN_DURATION, default_duration)
            size = values.get(_TRUN_SIZE, default_size)
            sample_flags = values.get(_TRUN_FLAGS, default_flags)
            if i == 0 and first_flags is not None:
                sample_flags = first_flags
            end = position + size
            if not any(start <= position and end <= stop for start, stop in mdats):
                raise ValueError(f"sample {i} [{position}, {end}) lies outside every mdat")
            samples.append(
                Sample(
                    decode_time=clock,
                    duration=duration,
                    composition_offset=values.get(_TRUN_COMPOSITION_OFFSET, 0),
                    keyframe=not sample_flags & _NON_SYNC_BIT,
                    data=data[position:end],
                )
            )
            position = end
            clock += duration
    info = FragmentInfo(sequence, track, decode_time, tuple(samples))
    return info, position
