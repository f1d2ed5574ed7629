"""The picture a viewer of ``upcast bench adaptive`` saw, against the game's ground truth.

During a case, ``StreamRecorder`` (the bench's one viewer on the relay) keeps what it
received of each session: the video fragments as they came (compressed: a few MB a
session), the init segment of every video track the catalog named (the encoded size
changes mid-stream), and the timing records, which tie a fragment's decode time to the
game time it shows and to the wall time it was rendered.

After the case, ``decoded_frames`` decodes each stream in order with PyAV, and
``score_stream`` compares, at sample times on a fixed game-time grid, the frame on
screen with the ground truth rendered at that game time at display size. The frame on
screen at game time ``g`` is the last frame received by the end of the run whose game
time is not after ``g``: a frame lost, skipped, never rendered (a lower frame rate) or
undecodable leaves the one before it on screen, and is scored so: a held frame of a
moving scene scores what a player sees, a picture that lags the game. How late the
frames came is measured separately (render to receive), not here.

The grid is absolute game time (every ``step`` seconds, half a frame period past the
frames' own times), so every case of a run samples the same instants and the ground
truth of each is rendered once per run.
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import av
import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from av.video.codeccontext import VideoCodecContext

from server.bench.serve import FrameCounter
from server.frames.frame import Size
from server.game.render.renderer import Renderer
from server.media.cmaf import find_box, iter_boxes
from server.media.cmaf_read import parse_fragment, track_defaults, track_timescales
from server.moq.events import Event, FrameReceived
from server.quic.moq_link import MoqLink
from server.session.timing_track import TRACK_NAME as TIMING_TRACK
from server.session.timing_track import decode_timing
from upscalers.metrics import psnr, ssim

U8 = npt.NDArray[np.uint8]
US = 1_000_000
# PSNR of identical pictures is infinite; a mean over samples needs a ceiling.
PSNR_CEILING_DB = 100.0


@dataclass
class RecordedStream:
    """One session's stream as the viewer received it."""

    inits: dict[str, bytes] = field(default_factory=dict)  # video track -> init segment
    fragments: list[tuple[float, str, bytes]] = field(default_factory=list)  # (at, track, data)
    # pts (us) -> (game time us, wall time rendered us), from the timing track
    frames: dict[int, tuple[int, int]] = field(default_factory=dict)
    received_wall_us: dict[str, list[int]] = field(default_factory=dict)  # track -> per fragment


class StreamRecorder(FrameCounter):
    """``FrameCounter`` that also keeps each session's video, init segments and timing."""

    def __init__(self) -> None:
        super().__init__()
        self.streams: dict[str, RecordedStream] = {}
        self._video_tracks: dict[int, tuple[str, str]] = {}  # subscription -> (broadcast, track)
        self._timing: dict[int, str] = {}  # timing subscription -> broadcast
        self.recording = True

    def subscribe(self, link: MoqLink, broadcasts: list[str]) -> None:
        for b in broadcasts:
            self.streams.setdefault(b, RecordedStream())
            self._timing[link.moq.subscribe(b, TIMING_TRACK)] = b
        super().subscribe(link, broadcasts)

    def stop(self) -> None:
        """Keep nothing more: frames after the measured window are not scored."""
        self.recording = False

    def on_events(self, link: MoqLink, events: list[Event]) -> None:
        super().on_events(link, events)
        if not self.recording:
            return
        now, wall_us = time.monotonic(), time.time_ns() // 1000
        for e in events:
            if not isinstance(e, FrameReceived):
                continue
            if (video := self._video_tracks.get(e.subscription_id)) is not None:
                stream = self.streams[video[0]]
                stream.fragments.append((now, video[1], e.payload))
                stream.received_wall_us.setdefault(video[1], []).append(wall_us)
            elif (timing := self._timing.get(e.subscription_id)) is not None:
                self._keep_timing(self.streams[timing], e.payload)

    def _watch(self, link: MoqLink, broadcast: str, track: str) -> None:
        super()._watch(link, broadcast, track)
        subscription, _ = self._video[broadcast]
        self._video_tracks[subscription] = (broadcast, track)

    def _follow(self, link: MoqLink, broadcast: str, catalog: bytes) -> None:
        with contextlib.suppress(ValueError, KeyError, TypeError, AttributeError):
            renditions = json.loads(catalog)["video"]["renditions"]
            stream = self.streams.setdefault(broadcast, RecordedStream())
            for track, rendition in renditions.items():
                stream.inits[str(track)] = base64.b64decode(rendition["container"]["init"])
        super()._follow(link, broadcast, catalog)

    @staticmethod
    def _keep_timing(stream: RecordedStream, payload: bytes) -> None:
        with contextlib.suppress(ValueError, KeyError, TypeError):
            record = decode_timing(payload)
            game_us = record.get("game_time_us")
            if record.get("kind", "video") != "video" or not isinstance(game_us, int):
                return
            stamps: dict[str, Any] = record.get("stamps") or {}
            rendered = stamps.get("render_start")
            stream.frames[int(record["pts_us"])] = (
                game_us,
                int(rendered) if isinstance(rendered, int) else 0,
            )


def avcc_of(init: bytes) -> bytes:
    """The avcC record (SPS and PPS) of an H.264 init segment; KeyError if absent."""
    stsd = find_box(init, [b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stsd"])
    entry = next(iter_boxes(init, stsd.payload_start + 8, stsd.end))  # after version, count
    # A visual sample entry has 78 bytes of fields before its child boxes.
    avcc = find_box(init, [b"avcC"], entry.payload_start + 78, entry.end)
    return init[avcc.payload_start : avcc.end]


@dataclass
class DecodeCounts:
    decoded: int = 0
    undecodable: int = 0  # fragments or pictures the decoder refused
    without_game_time: int = 0  # decoded, but no timing record said what game time


def decoded_frames(
    stream: RecordedStream, counts: DecodeCounts | None = None
) -> Iterator[tuple[int, U8]]:
    """(game time us, RGB picture) of every frame of ``stream`` the decoder returns, in
    the order received; a new video track (a new encoded size) starts a new decoder."""
    counts = counts if counts is not None else DecodeCounts()
    decoder: VideoCodecContext | None = None
    track_now: str | None = None
    timescale = US
    defaults: dict[int, Any] = {}
    for _, track, data in stream.fragments:
        if track != track_now:
            track_now, decoder = track, None
            init = stream.inits.get(track)
            try:
                if init is None:
                    raise KeyError(f"no init segment for track {track}")
                decoder = _decoder(init)
                timescale = next(iter(track_timescales(init).values()), US)
                defaults = track_defaults(init)
            except (KeyError, ValueError, StopIteration, av.FFmpegError):
                decoder = None
        if decoder is None:
            counts.undecodable += 1
            continue
        try:
            samples = parse_fragment(data, defaults).samples
        except ValueError:
            counts.undecodable += 1
            continue
        for sample in samples:
            # The timing record's pts_us is the fragment's decode time (server/session/
            # timing_track.py); upcast's streams have no composition offsets.
            pts_us = sample.decode_time * US // timescale
            packet = av.Packet(sample.data)
            packet.pts = pts_us
            try:
                pictures = decoder.decode(packet)
            except av.FFmpegError:
                counts.undecodable += 1
                continue
            for picture in pictures:
                known = stream.frames.get(int(picture.pts if picture.pts is not None else -1))
                if known is None:
                    counts.without_game_time += 1
                    continue
                counts.decoded += 1
                rgb: U8 = picture.to_ndarray(format="rgb24")  # type: ignore[assignment]
                yield known[0], rgb


def _decoder(init: bytes) -> VideoCodecContext:
    decoder = av.CodecContext.create("h264", "r")
    assert isinstance(decoder, VideoCodecContext)
    decoder.extradata = avcc_of(init)
    decoder.thread_count = 1  # frame threads would hold pictures back
    return decoder


def game_time_grid(first_us: int, last_us: int, step_s: float, offset_s: float = 0.0) -> list[int]:
    """Sample instants (us) in [first, last]: ``offset_s`` past the multiples of ``step_s``.

    The bench offsets them by half a frame period: a picture is on screen for its whole
    period, so an instant half-way through it is what a viewer sees on average, and an
    instant on a frame's own time would score a full-rate stream as if it had no lag."""
    step_us = max(1, round(step_s * US))
    offset_us = round(offset_s * US)
    k0 = -(-(first_us - offset_us) // step_us)  # ceiling division
    return [k * step_us + offset_us for k in range(k0, (last_us - offset_us) // step_us + 1)]


@dataclass
class PictureScore:
    psnr_db: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    at_us: list[int] = field(default_factory=list)  # the sample's game time
    shown_age_ms: list[float] = field(default_factory=list)  # sample - shown frame's game time

    def mean_psnr(self, where: Callable[[int], bool] = lambda _t: True) -> float | None:
        values = [v for v, t in zip(self.psnr_db, self.at_us, strict=True) if where(t)]
        return round(sum(values) / len(values), 2) if values else None

    def mean_ssim(self, where: Callable[[int], bool] = lambda _t: True) -> float | None:
        values = [v for v, t in zip(self.ssim, self.at_us, strict=True) if where(t)]
        return round(sum(values) / len(values), 4) if values else None


def score_stream(
    frames: Iterable[tuple[int, U8]], grid_us: Sequence[int], truth: Callable[[int], U8]
) -> PictureScore:
    """At each grid instant: the last frame whose game time is not after it, against
    ``truth(instant)``. Instants before the first frame are not scored (nothing was on
    screen yet); instants after the last are scored against the last (it stayed)."""
    score = PictureScore()
    points = iter(grid_us)
    point = next(points, None)
    shown: tuple[int, U8] | None = None

    def take(g: int, frame: tuple[int, U8]) -> None:
        reference = truth(g)
        picture = frame[1]
        if picture.shape != reference.shape:  # an encoded size below the display's
            picture = _stretch(picture, reference.shape[1], reference.shape[0])
        score.psnr_db.append(min(PSNR_CEILING_DB, psnr(reference, picture)))
        score.ssim.append(ssim(reference, picture))
        score.at_us.append(g)
        score.shown_age_ms.append((g - frame[0]) / 1000)

    for game_us, picture in frames:
        while point is not None and point < game_us:
            if shown is not None:
                take(point, shown)
            point = next(points, None)
        if point is None:
            break
        shown = (game_us, picture)
    while point is not None and shown is not None:
        take(point, shown)
        point = next(points, None)
    return score


def _stretch(picture: U8, width: int, height: int) -> U8:
    """A picture encoded below the display size, stretched to it bilinearly (as the
    page's canvas does) so it is scored against the display-size ground truth."""
    t = torch.from_numpy(np.ascontiguousarray(picture)).permute(2, 0, 1)[None].float()
    out = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False)
    return out[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def decode_times_us(stream: RecordedStream) -> list[int | None]:
    """Each received fragment's decode time in microseconds (the timing record's
    ``pts_us``), in ``stream.fragments`` order; None where its track's init segment is
    missing or the fragment does not parse. Each init segment is read once."""
    clocks: dict[str, tuple[int, dict[int, Any]] | None] = {}
    out: list[int | None] = []
    for _, track, data in stream.fragments:
        if track not in clocks:
            init = stream.inits.get(track)
            try:
                clocks[track] = (
                    None
                    if init is None
                    else (next(iter(track_timescales(init).values()), US), track_defaults(init))
                )
            except (KeyError, ValueError):
                clocks[track] = None
        clock = clocks[track]
        if clock is None:
            out.append(None)
            continue
        try:
            out.append(parse_fragment(data, clock[1]).decode_time * US // clock[0])
        except ValueError:
            out.append(None)
    return out


def render_to_receive_ms(stream: RecordedStream) -> list[float]:
    """Per received frame: wall time received minus wall time its render started (one
    machine, one clock), in ms, for frames whose timing record arrived."""
    out: list[float] = []
    received = {track: iter(walls) for track, walls in stream.received_wall_us.items()}
    for (_, track, _), pts in zip(stream.fragments, decode_times_us(stream), strict=True):
        wall = next(received.get(track, iter(())), None)
        known = stream.frames.get(pts) if pts is not None else None
        if wall is not None and known is not None and known[1] > 0:
            out.append((wall - known[1]) / 1000)
    return out


def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, math.ceil(q * len(ordered)) - 1)], 1)


class GroundTruth:
    """The game's ground truth at display size, rendered once per game-time instant."""

    def __init__(self, scene: str, display: tuple[int, int], *, seed: int = 0, ss: int = 3) -> None:
        self.scene, self.display, self.seed, self.ss = scene, display, seed, ss
        self._renderer: Renderer | None = None
        self._cache: dict[int, U8] = {}
        self.render_s = 0.0

    def __call__(self, game_us: int) -> U8:
        cached = self._cache.get(game_us)
        if cached is None:
            if self._renderer is None:
                # The render size is irrelevant: the ground truth has its own.
                self._renderer = Renderer(self.scene, Size(64, 36), seed=self.seed)
            started = time.perf_counter()
            cached = self._renderer.render_ground_truth(game_us / US, Size(*self.display), self.ss)
            self.render_s += time.perf_counter() - started
            self._cache[game_us] = cached
        return cached
