"""The ``timing`` track: one JSON frame per video frame with its stage stamps.

Stamps are wall-clock microseconds (the monotonic ones mean nothing outside
this machine), keyed by the stage labels of ``server/frames/timing.py``, only for
stages the frame reached. The browser and the load test add their own stages
(``client_receive``...) and compute every span the same way the server does.
``pts_us`` ties the record to the video frame (the CMAF decode time); ``n``
counts published frames so a viewer can tell what it lost.

``game_time_us`` is the game time the frame was rendered at, in microseconds
(``FrameMeta.game_time_us``; a predicted frame has its tick's time), so a benchmark
can re-render the ground truth of a received frame after the run: the frame id
alone does not tell the time once the frame rate has changed. It is left out when
0: unknown (a source without a game clock, the load test's synthetic frames), and
hence also for the one frame rendered at game time 0 itself.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from server.frames.frame import FrameFlags, FrameMeta
from server.frames.timing import Stage

if TYPE_CHECKING:
    from server.session.audio_capture import CapturedAudio

TRACK_NAME = "timing"


def timing_record(meta: FrameMeta, *, n: int, pts_us: int, keyframe: bool) -> dict[str, Any]:
    """``n`` counts published frames (0, 1, 2, ...): a gap is a frame a viewer lost."""
    stamps: dict[str, int] = {}
    for stage in Stage:
        wall_ns = int(meta.stamps[stage, 1])
        if wall_ns:
            stamps[stage.label] = wall_ns // 1000
    record: dict[str, Any] = {
        "frame": meta.frame_id,
        "n": n,
        "pts_us": pts_us,
        "keyframe": keyframe,
        "predicted": bool(meta.flags & FrameFlags.PREDICTED),
        "input_seq": meta.input_seq,
        "stamps": stamps,
    }
    if meta.game_time_us:
        record["game_time_us"] = meta.game_time_us
    return record


def audio_timing_record(captured: CapturedAudio, *, publish_us: int) -> dict[str, Any]:
    """One audio packet's stamps. ``kind`` tells it from a video record, and its time is
    ``audio_pts_us`` (not ``pts_us``) so no reader can mistake it for a video frame's.

    Stages: ``audio_sample`` (when its first sample happens in the game: the media
    clock's time of its pts), ``audio_capture`` (synthesised), ``audio_encode_start``,
    ``audio_encode_end``, ``audio_publish``; the player adds receive, decode and play."""
    stamps = captured.stamps
    return {
        "kind": "audio",
        "audio_pts_us": captured.packet.pts_us,
        "stamps": {
            "audio_sample": stamps.sample,
            "audio_capture": stamps.capture,
            "audio_encode_start": stamps.encode_start,
            "audio_encode_end": stamps.encode_end,
            "audio_publish": publish_us,
        },
    }


def encode_timing(record: dict[str, Any]) -> bytes:
    return json.dumps(record, separators=(",", ":")).encode()


def decode_timing(payload: bytes) -> dict[str, Any]:
    """Parse one timing frame; ValueError if it is not a timing record."""
    record = json.loads(payload)
    if not isinstance(record, dict) or not isinstance(record.get("stamps"), dict):
        raise ValueError("not a timing record")
    return record


def span_ms(record: dict[str, Any], start: str, end: str) -> float | None:
    """Milliseconds between two wall-clock stamps of a record, None if one is missing."""
    stamps = record["stamps"]
    a, b = stamps.get(start), stamps.get(end)
    if not isinstance(a, int) or not isinstance(b, int):
        return None
    return (b - a) / 1000.0
